"""`gd2p replay FILE.mcap --view`: a recording played in the live view, with pause and speed controls.

Plays the bus messages of a push's MCAP (services/planner/recording.py: its PushDecisions, robot states and
response) or of the recorder's (every publication: decisions, states, object tracks, held plans) into a
`LiveView` at the recorded pace times the view's "speed" slider; "pause" holds the clock, "restart" plays
it again from the start. Foreign channels (the Foxglove ones) are skipped.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Sequence

from shared.contracts.codec import CodecError
from shared.contracts.messages import ExecutionState, ObjectTrack, PlanHeld, PushDecision, PushResponse
from visualisation.live import LiveView
from visualisation.recording import Record, read_records

MIN_SLEEP_S = 0.005  # messages due within this are drawn together (robot states come at 500 Hz)


class ReplayPlayer:
    """Plays `paths` into `view`; `play()` returns when they are played (or `stop` is set)."""

    def __init__(self, view: LiveView, paths: Sequence[str], speed: float = 1.0, stop: threading.Event | None = None):
        self.view = view
        self.paths = list(paths)
        self.stop = stop or threading.Event()
        self.played = 0
        gui = view.server.gui
        with gui.add_folder("Replay"):
            self._clock = gui.add_markdown("")
            self.pause = gui.add_checkbox("Pause", False)
            self.speed = gui.add_slider("Speed", min=0.1, max=10.0, step=0.1, initial_value=float(speed))
            self._restart_button = gui.add_button("Restart")
        self.restart_requested = threading.Event()
        self._restart_button.on_click(lambda _event: self.restart_requested.set())

    def play(self) -> int:
        """Play every file once (again from the start whenever "Restart" is pressed meanwhile); the number of
        messages shown in the last pass."""
        while True:
            self.restart_requested.clear()
            self.played = self._play_once()
            if not self.restart_requested.is_set() or self.stop.is_set():
                return self.played

    def _play_once(self) -> int:
        records = [r for path in self.paths for r in read_records(path) if _shown(r)]
        if not records:
            return 0
        start_ns = records[0].log_time_ns
        span_s = (records[-1].log_time_ns - start_ns) / 1e9
        clock_s = 0.0  # recording time played so far
        last = time.monotonic()
        shown = 0
        for record in records:
            due_s = (record.log_time_ns - start_ns) / 1e9
            while clock_s < due_s - MIN_SLEEP_S:
                if self.stop.is_set() or self.restart_requested.is_set():
                    return shown
                time.sleep(min(0.05, max(MIN_SLEEP_S, (due_s - clock_s) / max(self.speed.value, 1e-3))))
                now = time.monotonic()
                if not self.pause.value:
                    clock_s += (now - last) * float(self.speed.value)
                last = now
                self._clock.content = f"{clock_s:.2f} s of {span_s:.2f} s{' (paused)' if self.pause.value else ''}"
            shown += _show(self.view, record)
        self._clock.content = f"{span_s:.2f} s of {span_s:.2f} s (done)"
        return shown


_TYPES = {"PushDecision", "ExecutionState", "ObjectTrack", "PlanHeld", "PushResponse"}


def _shown(record: Record) -> bool:
    return record.encoding.rsplit(";", 1)[-1] in _TYPES  # application/msgpack;<Type>


def _show(view: LiveView, record: Record) -> int:
    try:
        message = record.decode()
    except CodecError:
        return 0
    if isinstance(message, PushDecision):
        view.show_decision(message)
    elif isinstance(message, ExecutionState):
        view.show_state(message)
    elif isinstance(message, ObjectTrack):
        view.show_track(message)
    elif isinstance(message, PlanHeld):
        view.show_held(message)
    elif isinstance(message, PushResponse):
        view.show_response(message)
    else:
        return 0
    return 1
