"""Non-blocking zenoh telemetry publisher.

Navigation code calls :meth:`TelemetryPublisher.publish` from the asyncio loop. That call only
stamps the message with the daemon's clock, applies the stream's optional rate limit and
appends to a bounded in-memory queue (dropping the oldest message when full); it never touches
the network. A daemon worker thread owns every zenoh publisher: it takes messages from the
queue, encodes them (JSON, or the binary scan encoding for ``scan``) and puts them. A stuck or
failing zenoh therefore costs telemetry, never navigation time. Payload layout and key space:
docs/telemetry.md.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import orjson
import zenoh

from companion.telemetry.keys import SCHEMA_VERSION, STREAMS, key
from companion.telemetry.rate import RateWindow
from companion.telemetry.scan_codec import SCAN_ENCODING, encode_scan

logger = logging.getLogger("companion.telemetry")

ERROR_LOG_INTERVAL_S = 60.0
"""A failing stream is logged at most once per this many seconds of the publisher's clock."""

JSON_ENCODING = "application/json"
ENCODINGS: dict[str, tuple[Callable[[float, dict[str, Any]], bytes], str]] = {
    "scan": (encode_scan, SCAN_ENCODING),
}
"""(encoder, zenoh encoding) of the streams that are not JSON; the encoder turns (t, payload) into bytes."""


@dataclass(slots=True)
class _StreamState:
    """Counters and rate-limit state of one stream. Times are on the publisher's clock (s)."""

    stream: str
    key: str
    min_interval_s: float  # 0.0 when the stream has no rate limit
    next_due_t: float | None = None  # earliest time the rate limit accepts the next message
    offered: int = 0
    published: int = 0
    dropped: int = 0
    rate_limited: int = 0
    errors: int = 0
    last_publish_t: float | None = None
    last_error_log_t: float | None = None
    publish_times: RateWindow = field(default_factory=RateWindow)


class TelemetryPublisher:
    """Publish telemetry streams of one vehicle on ``uav/<sysid>/<stream>`` without blocking.

    Per stream it counts, see :meth:`stats`:

    * ``offered``: valid :meth:`publish` calls;
    * ``rate_limited``: calls refused because the stream's maximum rate was exceeded;
    * ``dropped``: accepted messages discarded unsent, because the queue was full (the oldest
      queued message goes, whichever its stream) or :meth:`close` ran out of time;
    * ``errors``: messages whose encoding or zenoh put raised;
    * ``published``: messages handed to zenoh (delivery to subscribers is best effort);
    * ``last_publish_t``: clock time (s) the last put returned, ``None`` before the first;
    * ``age_s``: seconds since then, ``None`` before the first;
    * ``rate_hz``: messages published per second over the last 5 s (``RATE_WINDOW_S``).

    With ``session=None`` telemetry is disabled: :meth:`publish` validates, rate-limits and
    counts ``offered``/``rate_limited``, and nothing is queued. The same holds after
    :meth:`close`.
    """

    def __init__(
        self,
        session: zenoh.Session | None,
        sysid: int,
        queue_size: int = 256,
        max_rate_hz: dict[str, float] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """Create the publisher and, when ``session`` is given, start its worker thread.

        Args:
            session: an open zenoh session, or ``None`` to disable telemetry. The caller keeps
                ownership and closes it after :meth:`close`.
            sysid: the vehicle's MAVLink system id (1..255), the ``<sysid>`` of every key.
            queue_size: maximum number of messages waiting for the worker, all streams
                together.
            max_rate_hz: optional maximum rate per stream in Hz. Accepted messages follow a
                schedule of one per ``1 / rate`` seconds (so a 50 Hz producer limited to 20 Hz
                gets 20 Hz, not every third tick); a message before the stream's next slot is
                refused, and none is accepted within half a period of the previous one.
            clock: the daemon's monotonic clock in seconds; it stamps ``"t"`` and drives the
                rate limits, ``last_publish_t`` and error-log throttling.

        Raises:
            ValueError: invalid ``sysid``, ``queue_size`` < 1, an unknown stream in
                ``max_rate_hz`` or a rate that is not a finite number > 0.
        """
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        rates = max_rate_hz or {}
        for stream, hz in rates.items():
            if stream not in STREAMS:
                raise ValueError(f"max_rate_hz names an unknown stream {stream!r}")
            if not (math.isfinite(hz) and hz > 0.0):
                raise ValueError(f"max_rate_hz[{stream!r}] must be finite and > 0, got {hz!r}")
        self._streams = {
            stream: _StreamState(
                stream=stream,
                key=key(sysid, stream),
                min_interval_s=1.0 / rates[stream] if stream in rates else 0.0,
            )
            for stream in STREAMS
        }
        self._sysid = sysid
        self._queue_size = queue_size
        self._clock = clock
        self._queue: deque[tuple[_StreamState, float, dict[str, Any]]] = deque()
        self._cv = threading.Condition()
        self._closing = False
        self._drain_deadline = math.inf  # time.monotonic() after which close() stops draining
        self._worker: threading.Thread | None = None
        # Called with (stream, t, payload) for every message that passes its rate limit, zenoh or not
        # (the flight recorder); on the caller's thread, so it must be as quick as publish itself.
        self.observer: Callable[[str, float, dict[str, Any]], None] | None = None
        if session is not None:
            self._worker = threading.Thread(
                target=self._run,
                args=(session,),
                name=f"telemetry-publisher-{sysid}",
                daemon=True,
            )
            self._worker.start()

    def add_streams(self, streams: tuple[str, ...]) -> None:
        """Allow ``streams`` besides :data:`~companion.telemetry.keys.STREAMS` (those a pipeline
        declares in ``telemetry_streams``; JSON-encoded, no rate limit). Call before publishing them.

        Raises:
            ValueError: a name that is not a lower-case word.
        """
        for stream in streams:
            if stream not in self._streams:
                state = _StreamState(stream=stream, key=key(self._sysid, stream, streams), min_interval_s=0.0)
                with self._cv:
                    self._streams[stream] = state

    def publish(self, stream: str, payload: dict[str, Any]) -> None:
        """Queue one message of ``stream``; returns at once, O(1), never does I/O.

        The message is stamped ``"t" = clock()`` now and encoded later by the worker, so the
        caller hands ``payload`` over and must not mutate it (nor arrays inside it) afterwards.
        Values may be Python or numpy scalars, numpy arrays, lists, tuples and dicts; NaN and
        infinities are sent as ``null``.

        Raises:
            ValueError: ``stream`` is not a known stream, or ``payload`` has a ``"v"`` or
                ``"t"`` key (reserved for the envelope). Both are programming errors.
        """
        state = self._streams.get(stream)
        if state is None:
            raise ValueError(f"unknown telemetry stream {stream!r}")
        if "v" in payload or "t" in payload:
            raise ValueError(f"payload of {stream!r} uses a reserved key 'v' or 't'")
        now = self._clock()
        with self._cv:
            state.offered += 1
            if state.next_due_t is not None and now < state.next_due_t:
                state.rate_limited += 1
                return
            interval = state.min_interval_s
            state.next_due_t = (now + interval if state.next_due_t is None
                                else max(state.next_due_t + interval, now + interval / 2))
            if self.observer is not None:
                self.observer(stream, now, payload)
            if self._worker is None or self._closing:
                return
            if len(self._queue) >= self._queue_size:
                oldest = self._queue.popleft()
                oldest[0].dropped += 1
            self._queue.append((state, now, payload))
            self._cv.notify()

    def due(self, stream: str) -> bool:
        """Whether a message of ``stream`` offered now would pass the stream's rate limit.

        Lets a producer skip building a costly payload; counts nothing. Always True for a
        stream without a rate limit.
        """
        state = self._streams[stream]
        with self._cv:
            return state.next_due_t is None or self._clock() >= state.next_due_t

    def stats(self) -> dict[str, dict[str, int | float | None]]:
        """Snapshot of every stream's counters (see the class docstring), keyed by stream."""
        now = self._clock()
        with self._cv:
            return {
                stream: {
                    "offered": s.offered,
                    "published": s.published,
                    "dropped": s.dropped,
                    "rate_limited": s.rate_limited,
                    "errors": s.errors,
                    "last_publish_t": s.last_publish_t,
                    "age_s": None if s.last_publish_t is None else max(0.0, now - s.last_publish_t),
                    "rate_hz": s.publish_times.rate_hz(now),
                }
                for stream, s in self._streams.items()
            }

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop the worker: send what is queued for up to ``timeout_s / 2``, then undeclare.

        Returns within about ``timeout_s`` seconds even if a zenoh put never returns: the
        worker is then abandoned (it is a daemon thread), logged, and finishes on its own if the
        put ever returns. Messages still queued at the deadline count as ``dropped``. Later
        :meth:`publish` calls only count. Idempotent.
        """
        with self._cv:
            if not self._closing:
                self._closing = True
                self._drain_deadline = time.monotonic() + timeout_s / 2
                self._cv.notify()
        if self._worker is None:
            return
        self._worker.join(timeout_s)
        if self._worker.is_alive():
            logger.warning(
                "telemetry worker still blocked in zenoh after %.1f s; abandoning it", timeout_s
            )

    def _run(self, session: zenoh.Session) -> None:
        """Worker thread: send queued messages until closed, then undeclare the publishers."""
        publishers: dict[str, zenoh.Publisher] = {}
        try:
            while True:
                with self._cv:
                    while not self._queue and not self._closing:
                        self._cv.wait()
                    if not self._queue:
                        return
                    if self._closing and time.monotonic() >= self._drain_deadline:
                        for state, _, _ in self._queue:
                            state.dropped += 1
                        self._queue.clear()
                        return
                    state, t, payload = self._queue.popleft()
                self._send(session, publishers, state, t, payload)
        finally:
            for publisher in publishers.values():
                try:
                    publisher.undeclare()
                except Exception as exc:  # noqa: BLE001 - the session may be closed already
                    logger.debug("undeclaring a telemetry publisher failed: %s", exc)

    def _send(
        self,
        session: zenoh.Session,
        publishers: dict[str, zenoh.Publisher],
        state: _StreamState,
        t: float,
        payload: dict[str, Any],
    ) -> None:
        """Encode one message and put it on its stream's publisher (declared on first use)."""
        try:
            encode, encoding = ENCODINGS.get(state.stream, (encode_json, JSON_ENCODING))
            data = encode(t, payload)
            publisher = publishers.get(state.key)
            if publisher is None:
                publisher = session.declare_publisher(
                    state.key,
                    encoding=zenoh.Encoding(encoding),
                    congestion_control=zenoh.CongestionControl.DROP,
                )
                publishers[state.key] = publisher
            publisher.put(data)
        except Exception as exc:  # noqa: BLE001 - nothing may kill the worker
            state.errors += 1
            now = self._clock()
            last_log_t = state.last_error_log_t
            if last_log_t is None or now - last_log_t >= ERROR_LOG_INTERVAL_S:
                state.last_error_log_t = now
                logger.warning(
                    "telemetry %s: publishing failed (%d errors so far, logged at most every "
                    "%.0f s): %s: %s",
                    state.key,
                    state.errors,
                    ERROR_LOG_INTERVAL_S,
                    type(exc).__name__,
                    exc,
                )
            return
        now = self._clock()
        with self._cv:  # stats() reads these from another thread
            state.published += 1
            state.last_publish_t = now
            state.publish_times.add(now)


def encode_json(t: float, payload: dict[str, Any]) -> bytes:
    """UTF-8 JSON of the envelope ``{"v": SCHEMA_VERSION, "t": t, **payload}``, compact.

    numpy scalars and arrays become JSON numbers, booleans and (nested) arrays; NaN and
    infinities become ``null``; tuples become arrays; non-string dict keys become strings.
    orjson does all of it in C (numpy arrays natively, a non-contiguous one through
    :func:`_numpy_default`), 2-10x faster than the json module on these messages.

    Raises:
        TypeError: a value of another type (e.g. a datetime or an arbitrary object).
    """
    document = {"v": SCHEMA_VERSION, "t": t, **payload}
    return orjson.dumps(document, default=_numpy_default, option=orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS)


def _numpy_default(value: Any) -> Any:
    """What orjson does not encode itself: a numpy array it refuses (not C-contiguous, float16...)
    as (nested) lists, a numpy scalar as its Python value; anything else is a TypeError."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"cannot encode {type(value).__name__} as telemetry JSON")
