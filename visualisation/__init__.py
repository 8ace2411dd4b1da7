"""Visualisation, outside the common library: CPU pictures of scenes (`render`) and MCAP files of bus traffic (`recording`).

A library the CLI, the planner's and recorder's recordings and the evaluation use; `shared` never imports it.
"""
