"""Leases: a holder's liveliness token that others watch, and lose within a bounded time.

A lease is a Zenoh liveliness token on `gd2p/lease/<role>/<identity>/<holder>` (`lease_key`). The role
names what the holder does (`planner` commands the robot; `client` is a push client waiting for its
answer); the identity is the holder's (its certificate's CN in the secure profile: LEASE_IDENTITIES
gives each role's default, the only identity that holds it today); `<holder>` is a random part (per
command, per client). The secure profile lets an identity declare tokens only under
`gd2p/lease/<role>/<its own identity>/*`, and only for a role it may hold, which binds a lease to an
identity: one `cli` cannot hold another client identity's lease, nor a planner's. Zenoh consolidates
tokens declared twice on one key, so a second holder cannot be counted: the random part makes the key
one nobody else holds.

`LeaseMonitor` watches one lease and sets `lost` when
- it is not confirmed within `startup_s` (a liveliness query that finds the token; a token just
  declared may take a moment to reach the router, so the query is repeated);
- its token is deleted (the holder undeclared it, closed its session or died): the monitor's
  liveliness subscriber sees the DELETE as soon as the router forwards it;
- this session loses its router (`session.info.routers_zid()` empties when the link closes: a
  router that died or was restarted), checked every `check_period_s`;
- the `RouterWatchdog` it was given reports the router silent for longer than its bound (a hung
  router or a network that drops packets without closing the link; without a watchdog that case
  waits for Zenoh's link lease, 10 s by default).

Measured (bench/chaos.py, tests/test_lease.py): liveliness queries are not a reliable liveness
signal — a client answers them from its local table, with its own token still listed after the
router died, and now and then with nothing while the router updates its routes — so the monitor
uses them only to confirm the token once.
"""
from __future__ import annotations

import contextlib
import hashlib
import hmac
import logging
import secrets
import struct
import threading
import time
from collections import Counter, deque
from collections.abc import Callable

import zenoh

from shared.bus.errors import BusError
from shared.bus.keys import LEASE_PREFIX, WATCHDOG_PREFIX, check_chunk

log = logging.getLogger("gd2p.bus.lease")

CHECK_PERIOD_S = 0.02
WATCHDOG_PERIOD_S = 0.02
WATCHDOG_BOUND_S = 0.3  # see RouterWatchdog
STARTUP_S = 1.0
QUERY_TIMEOUT_S = 0.15
LEASE_ROLES: tuple[str, ...] = ("planner", "client")  # who may hold a lease (the secure ACL binds each to an identity)
# Role -> the identity a lease of that role names when its holder gives none: the planner's certificate, and
# the "cli" certificate every push client carries (the plain profile has no certificates: the same names).
LEASE_IDENTITIES: dict[str, str] = {"planner": "planner", "client": "cli"}
ZID_BYTES = 16  # a Zenoh session id (ZenohId: 128 bits)
BEAT_FORMAT = f"!Q{ZID_BYTES}s32s"  # a watchdog beat: number, the probe session's zid, HMAC-SHA256 (RouterWatchdog)
BEAT_BYTES = struct.calcsize(BEAT_FORMAT)  # 56


class LeaseError(BusError):
    """A lease key is malformed (not `gd2p/lease/<role>/<identity>/<holder>`, or a wildcard)."""


def lease_key(role: str, holder: str, identity: str | None = None) -> str:
    """`gd2p/lease/<role>/<identity>/<holder>`: where `identity`, holding a lease of `role`, declares its token
    (`identity` defaults to the role's, LEASE_IDENTITIES)."""
    if role not in LEASE_ROLES:
        raise LeaseError(f"unknown lease role {role!r}; roles: {', '.join(LEASE_ROLES)}")
    try:
        who = check_chunk(LEASE_IDENTITIES[role] if identity is None else identity, "lease identity")
        return f"{LEASE_PREFIX}/{role}/{who}/{check_chunk(holder, 'lease holder')}"
    except BusError as exc:
        raise LeaseError(str(exc)) from None


def parse_lease_key(key: str) -> tuple[str, str]:
    """(role, holder) of a lease key; LeaseError unless it is exactly `gd2p/lease/<role>/<identity>/<holder>`
    (`lease_identity` gives the identity)."""
    role, _, holder = _lease_parts(key)
    return role, holder


def lease_identity(key: str) -> str:
    """The identity a lease key names (LeaseError for a malformed key)."""
    return _lease_parts(key)[1]


def _lease_parts(key: str) -> tuple[str, str, str]:
    parts = str(key).split("/")
    if len(parts) != 5 or "/".join(parts[:2]) != LEASE_PREFIX:
        raise LeaseError(f"lease {key!r} is not a key of the form {LEASE_PREFIX}/<role>/<identity>/<holder>")
    try:
        lease_key(parts[2], parts[4], parts[3])
    except BusError as exc:
        raise LeaseError(f"lease {key!r}: {exc}") from None
    return parts[2], parts[3], parts[4]


def lease_present(session: zenoh.Session, key: str, timeout_s: float = QUERY_TIMEOUT_S) -> bool:
    """True if a liveliness query finds a token declared on exactly `key` (a single look: see the module docstring)."""
    return any(reply.ok is not None and str(reply.ok.key_expr) == key
               for reply in session.liveliness().get(key, timeout=timeout_s))


def lease_alive(session: zenoh.Session, key: str, timeout_s: float = STARTUP_S) -> bool:
    """True if the lease key `key` is found held within `timeout_s` (LeaseError for a malformed key)."""
    parse_lease_key(key)
    deadline = time.monotonic() + timeout_s
    while True:
        if lease_present(session, key, min(QUERY_TIMEOUT_S, timeout_s)):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)


def has_router(session: zenoh.Session) -> bool:
    """True while the session has a link to a router (local: no message is sent)."""
    return any(True for _ in session.info.routers_zid())


def zid_bytes(zid: zenoh.ZenohId) -> bytes:
    """A session id as the `ZID_BYTES` bytes a watchdog beat carries (its text form is hex, leading zeros left out)."""
    return int(str(zid), 16).to_bytes(ZID_BYTES, "big")


class RouterWatchdog:
    """Is the router still forwarding? A probe session publishes a numbered beat every `period_s` on a key
    of its own; the watched session receives them. A beat can only arrive through the router, so
    `silence_s()` — how long the oldest beat not yet heard back has been out — grows from the moment
    the router stops forwarding, however the link looks; the router is blamed when it passes
    `bound_s` twice, `period_s` apart: at most `bound_s + 2 * period_s` after the router stopped
    (0.34 s by default, plus the monitor's check period; bench/chaos.py `router_hung` measures it).
    The bound is 0.3 s, not less: at 0.13 s the watchdog blamed a healthy router now and then while
    the 2-core machine ran the test suite (CPU starvation of the whole process, seen twice in 30+
    runs); a false alarm stops a push, so the default trades 0.17 s of reaction for none.

    It counts unanswered beats, not the time since the last one was heard, so that a process that was
    itself busy does not blame the router: a C call holding Python's GIL (PyBullet loading a world
    takes 0.3 s) stops this process's beats and callbacks alike. Beats are queued by Zenoh outside
    Python (a ring channel, drained by `silence_s()` and the beat thread), so the ones that came back
    while the process was busy count as heard, and none were sent meanwhile.

    Only this watchdog's own beats count (a single beat numbered 2^64-1 from anyone else used to
    mark every later beat as heard, so a frozen router went unnoticed). A beat is `BEAT_FORMAT`: the
    beat number, the probe session's id (zid, 16 bytes) and an HMAC-SHA256 of both under a random secret
    made for this watchdog, which never leaves the process. A beat of another length, another zid or a
    wrong MAC is ignored, and so is a number ahead of the last beat sent; `ignored` counts them by
    reason. What another session can still send is a copy of a beat it saw (a replay): it is numbered
    at most the last one sent and it came through the router, so it shows nothing the real beat did
    not. A flood of foreign beats can push real ones out of the ring channel: that looks like silence
    and stops the robot (safe); the secure profile lets only the bridge's identity put on the key.

    The probe session must be a second session to the same router (a session delivers its own
    publications locally). `close()` undeclares both ends; the sessions stay the caller's.
    """

    def __init__(self, session: zenoh.Session, probe: zenoh.Session, name: str, period_s: float = WATCHDOG_PERIOD_S,
                 bound_s: float = WATCHDOG_BOUND_S):
        if period_s <= 0 or bound_s <= 0:
            raise ValueError("period_s and bound_s must be positive")
        self.key = f"{WATCHDOG_PREFIX}/{check_chunk(name, 'watchdog name')}"
        self.period_s, self.bound_s = period_s, bound_s
        self.probe_zid = zid_bytes(probe.zid())
        self._secret = secrets.token_bytes(32)  # never sent, never logged: only this process can sign a beat
        self.ignored: Counter[str] = Counter()  # beats not counted, by reason: "length", "zid", "mac", "ahead"
        self._unanswered: deque[tuple[int, float]] = deque()  # (number, time sent) of beats not heard back yet
        self._heard = 0  # the newest beat heard back
        self._sent = 0  # the newest beat numbered for sending (no beat numbered higher is accepted)
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._subscriber = session.declare_subscriber(self.key, zenoh.handlers.RingChannel(64))
        self._publisher = probe.declare_publisher(self.key, congestion_control=zenoh.CongestionControl.DROP)
        self._thread = threading.Thread(target=self._beat, name="router-watchdog", daemon=True)
        self._thread.start()

    def _mac(self, number: int, zid: bytes) -> bytes:
        return hmac.new(self._secret, struct.pack("!Q", number) + zid, hashlib.sha256).digest()

    def _signed(self, number: int) -> bytes:
        """The beat numbered `number`, as the probe publishes it."""
        return struct.pack(BEAT_FORMAT, number, self.probe_zid, self._mac(number, self.probe_zid))

    def _beat(self) -> None:
        seq = 0
        while not self._closed.wait(self.period_s):
            seq += 1
            with self._lock:  # numbered before the put: its echo may be drained before the put returns
                self._sent = seq
            try:
                self._publisher.put(self._signed(seq))
            except zenoh.ZError:  # no router: the silence says so
                pass
            with self._lock:  # timed from after the put: a pause before it is this process's, not the router's
                self._unanswered.append((seq, time.monotonic()))
                self._drain()

    def _accept(self, beat: bytes) -> int | None:
        """The number of `beat` if it is one of this watchdog's own, sent already; None (counted) otherwise."""
        if len(beat) != BEAT_BYTES:
            reason = "length"
        else:
            number, zid, mac = struct.unpack(BEAT_FORMAT, beat)
            if not hmac.compare_digest(zid, self.probe_zid):
                reason = "zid"
            elif not hmac.compare_digest(mac, self._mac(number, zid)):
                reason = "mac"
            elif number > self._sent:
                reason = "ahead"
            else:
                return int(number)
        if not self.ignored[reason]:
            log.warning("router watchdog %s: ignoring a beat that is not its own (%s)", self.key, reason)
        self.ignored[reason] += 1
        return None

    def _drain(self) -> None:
        """Forget every beat up to the newest one heard back (beats overtaken or dropped included)."""
        while (sample := self._subscriber.try_recv()) is not None:
            number = self._accept(sample.payload.to_bytes())
            if number is not None:
                self._heard = max(self._heard, number)
        while self._unanswered and self._unanswered[0][0] <= self._heard:
            self._unanswered.popleft()

    def silence_s(self) -> float:
        """How long the oldest beat not yet heard back has been out (0 when every beat came back).

        A figure over `bound_s` is measured again after `period_s`: a pause of this whole process (the
        OS, a garbage collection) can leave echoes unread in the socket for a moment after it ends.
        """
        silence = self._measure()
        if silence > self.bound_s and not self._closed.wait(self.period_s):
            silence = self._measure()
        return silence

    def _measure(self) -> float:
        now = time.monotonic()  # before draining: a pause while draining must not count as silence
        with self._lock:
            self._drain()
            return max(0.0, now - self._unanswered[0][1]) if self._unanswered else 0.0

    def close(self) -> None:
        self._closed.set()
        self._thread.join(timeout=1.0)
        with contextlib.suppress(zenoh.ZError):
            self._publisher.undeclare()
        with contextlib.suppress(zenoh.ZError):
            self._subscriber.undeclare()


class LeaseMonitor:
    """Watch the lease `key` from construction until `close()`; see the module docstring.

    `lost` is set (and `on_lost` called once, on a monitor thread: keep it quick) at the first sign of
    loss; `reason` says which. Construct it *before* checking anything that the lease guards, so no
    loss between the check and the action goes unseen; `wait_confirmed()` is the check that it is held.
    """

    def __init__(self, session: zenoh.Session, key: str, *, on_lost: Callable[[], None] | None = None,
                 watchdog: RouterWatchdog | None = None, check_period_s: float = CHECK_PERIOD_S,
                 startup_s: float = STARTUP_S):
        parse_lease_key(key)
        if check_period_s <= 0 or startup_s <= 0:
            raise ValueError("check_period_s and startup_s must be positive")
        self.key = key
        self.session = session
        self.watchdog = watchdog
        self.check_period_s, self.startup_s = check_period_s, startup_s
        self.lost = threading.Event()
        self.confirmed = threading.Event()
        self.reason = ""
        self.lost_at: float | None = None  # time.monotonic() of the loss
        self._on_lost = on_lost
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._needs_router = has_router(session)  # a peer or router session has no router to lose
        self._subscriber = session.liveliness().declare_subscriber(key, self._on_sample, history=True)
        self._thread = threading.Thread(target=self._watch, name="lease-monitor", daemon=True)
        self._thread.start()

    @property
    def bound_s(self) -> float:
        """The longest a loss can go unnoticed once the lease is confirmed, a deleted token aside (noticed as
        soon as the router forwards the DELETE): a lost link within `check_period_s`, a router that stopped
        forwarding within the watchdog's `bound_s + 2 * period_s` more. Without a watchdog, a hung router waits
        for Zenoh's link lease (10 s by default), which this figure leaves out."""
        watchdog = self.watchdog
        return self.check_period_s + (2 * watchdog.period_s + watchdog.bound_s if watchdog is not None else 0.0)

    def wait_confirmed(self, timeout_s: float | None = None) -> bool:
        """Block until the lease is confirmed held (True), or lost / `timeout_s` passed (False)."""
        deadline = time.monotonic() + (self.startup_s if timeout_s is None else timeout_s)
        while not self.lost.is_set() and time.monotonic() < deadline:
            if self.confirmed.wait(0.005):
                return not self.lost.is_set()
        return self.confirmed.is_set() and not self.lost.is_set()

    def _on_sample(self, sample: zenoh.Sample) -> None:  # zenoh callback: set events only
        if sample.kind == zenoh.SampleKind.DELETE:
            self._lose("its token was deleted (the holder left, or the router dropped it)")
        else:
            self.confirmed.set()

    def _watch(self) -> None:
        started = time.monotonic()
        while not self._closed.is_set() and not self.lost.is_set():
            reason = self._link_problem()
            if reason is None and not self.confirmed.is_set():
                reason = self._confirm(started)
            if reason is not None:
                self._lose(reason)
                return
            self._closed.wait(self.check_period_s)

    def _link_problem(self) -> str | None:
        if self._needs_router and not has_router(self.session):
            return "this session lost its router"
        if self.watchdog is not None:
            silence = self.watchdog.silence_s()
            if silence > self.watchdog.bound_s:
                return f"the router forwarded nothing for {silence:.2f} s"
        return None

    def _confirm(self, started: float) -> str | None:
        try:
            if lease_present(self.session, self.key):
                self.confirmed.set()
                return None
        except zenoh.ZError as exc:
            return f"the bus failed: {exc}"
        if time.monotonic() - started >= self.startup_s:
            return f"nobody holds it (not found for {self.startup_s:.1f} s)"
        return None

    def _lose(self, why: str) -> None:
        with self._lock:
            if self.lost.is_set() or self._closed.is_set():
                return
            self.reason = f"lease {self.key!r} lost: {why}"
            self.lost_at = time.monotonic()
            self.lost.set()
        log.warning("%s", self.reason)
        if self._on_lost is not None:
            try:
                self._on_lost()
            except Exception:  # the callback is the caller's; the loss is recorded whatever it does
                log.exception("lease on_lost callback failed")

    def close(self) -> None:
        self._closed.set()
        try:
            self._subscriber.undeclare()
        except zenoh.ZError:  # the session is already closed
            pass
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=1.0)

    def __enter__(self) -> LeaseMonitor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
