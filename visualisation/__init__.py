"""Visualisation, outside the common library: CPU pictures of scenes (`render`) and MCAP files of bus traffic (`recording`).

A library (not a service) used by the CLI (`gd2p show`, `gd2p replay`), the planner's push recordings and the
recorder service; `shared` never imports it.
"""
