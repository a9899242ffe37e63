"""The physics loop of the simulation node: one thread that steps, and runs requests between steps.

One thread owns the simulation: it calls ``step()`` at ``rate_hz`` on the steady clock
(``realtime``; absolute deadlines, so the average rate is ``rate_hz`` whenever the steps take
less than a period on average: a late step is made up by starting the next ones at once, up to
``CATCH_UP`` periods behind; further behind, the schedule moves on instead of bursting), or back
to back (not ``realtime``). Everything else that
touches the simulation (reset, cut, pause, a snapshot for display) is a request run by
:meth:`PhysicsLoop.call` on that thread between two steps, under :attr:`PhysicsLoop.lock`,
so the simulation is touched by one thread at a time and never in the middle of a step.
Requests queued together are all served at the next step boundary, in order; a run of
consecutive requests with the same ``key`` is served once and all get the same answer
(100 resets at once reset once). A request not started within its timeout is withdrawn and
answered as not served. While paused or sleeping until the next deadline the loop serves
requests as they come.

Rate bookkeeping (:meth:`PhysicsLoop.rates`): steps per second and real-time factor over the
last ``window_s``, from the steps' start times and the simulated time each advanced.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Callable

CATCH_UP = 2.0  # periods a late realtime loop makes up by stepping at once; beyond, the schedule moves on


class _Request:
    __slots__ = ("fn", "key", "done", "ok", "result", "started", "withdrawn", "lock")

    def __init__(self, fn, key):
        self.fn, self.key = fn, key
        self.done = threading.Event()
        self.ok, self.result = False, None
        self.started = self.withdrawn = False
        self.lock = threading.Lock()


class PhysicsLoop:
    """A stepping thread. ``step()`` takes one step and returns the simulated time it advanced
    [s]; ``between()`` (optional) runs at every pass of the loop, between steps, under the lock;
    ``on_error(text)`` reports a step that raised (the loop goes on after a pause of a period)."""

    def __init__(self, step: Callable[[], float], rate_hz: float, realtime: bool = True,
                 between: Callable[[], None] | None = None, on_error: Callable[[str], None] | None = None,
                 window_s: float = 2.0, name: str = "physics"):
        self._step, self._between, self._on_error = step, between, on_error
        self.lock = threading.RLock()  # held while the simulation is touched: a step, a request
        self._cond = threading.Condition()
        self._queue: list[_Request] = []
        self._running = False
        self._paused = False
        self._thread = None
        self._name = name
        self.set_rate(rate_hz, realtime)
        self.window_s = float(window_s)
        self._history = collections.deque()  # (start time, advanced sim time) of recent steps
        self.steps = 0  # steps taken since start
        self.late_steps = 0  # realtime: steps that started more than a period after their deadline
        self.step_s_total = 0.0
        self.step_s_max = 0.0  # longest step in the current window of rates()
        self._step_s_window = collections.deque()
        self.last_error = ""

    # --------------------------------------------------------------- control
    def set_rate(self, rate_hz: float, realtime: bool) -> None:
        rate_hz = float(rate_hz)
        if not rate_hz > 0.0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        with self._cond:
            self.rate_hz, self.realtime = rate_hz, bool(realtime)
            self._reschedule = True
            self._cond.notify_all()

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def paused(self) -> bool:
        return self._paused

    def set_paused(self, paused: bool) -> None:
        """Stop or resume stepping (call it through :meth:`call` to apply it between steps)."""
        with self._cond:
            if self._paused != bool(paused):
                self._history.clear()
                self._step_s_window.clear()
            self._paused = bool(paused)
            self._reschedule = True
            self._cond.notify_all()

    @property
    def running(self) -> bool:
        return self._running

    def start(self) -> None:
        with self._cond:
            if self._running:
                return
            self._running = True
        self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> None:
        """Stop after the step in progress; queued requests are answered as not served."""
        with self._cond:
            self._running = False
            pending, self._queue = self._queue, []
            self._cond.notify_all()
        for r in pending:
            self._finish(r, False, "the node is shutting down")
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def wake(self) -> None:
        """Make a sleeping loop pass once (e.g. to serve ``between`` work now)."""
        with self._cond:
            self._cond.notify_all()

    # -------------------------------------------------------------- requests
    def call(self, fn: Callable[[], object], timeout: float, key=None) -> tuple[bool, object]:
        """Run ``fn()`` on the loop's thread between two steps; wait for it at most ``timeout``
        seconds to start. Returns (True, its result) or (False, the reason it failed or was not
        served). From the loop's own thread (or with the loop stopped) ``fn`` runs at once."""
        if threading.current_thread() is self._thread or not self._running:
            with self.lock:
                return self._execute(fn)
        req = _Request(fn, key)
        with self._cond:
            if not self._running:
                return False, "the node is shutting down"
            self._queue.append(req)
            self._cond.notify_all()
        if not req.done.wait(timeout):
            with req.lock:
                if not req.started:
                    req.withdrawn = True
            if req.withdrawn:
                with self._cond:
                    if req in self._queue:
                        self._queue.remove(req)
                return False, (f"not served within {timeout:g} s: the simulation did not reach a step boundary "
                               f"(the step in progress takes longer; see service_timeout_s)")
            req.done.wait()
        return req.ok, req.result

    @staticmethod
    def _execute(fn):
        try:
            return True, fn()
        except Exception as exc:  # noqa: BLE001 - the caller gets the reason
            return False, f"{type(exc).__name__}: {exc}" if not isinstance(exc, ValueError) else str(exc)

    @staticmethod
    def _finish(req, ok, result):
        req.ok, req.result = ok, result
        req.done.set()

    def _serve(self) -> None:
        with self._cond:
            batch, self._queue = self._queue, []
        prev = None  # (key, ok, result) of the last request served in this batch
        for req in batch:
            with req.lock:
                if req.withdrawn:
                    continue
                req.started = True
            if prev is not None and req.key is not None and req.key == prev[0]:
                self._finish(req, prev[1], prev[2])
                continue
            with self.lock:
                ok, result = self._execute(req.fn)
            self._finish(req, ok, result)
            prev = (req.key, ok, result)

    # ------------------------------------------------------------------ loop
    def _run(self) -> None:
        deadline = time.monotonic()
        while self._running:
            self._serve()
            if self._between is not None:
                with self.lock:
                    try:
                        self._between()
                    except Exception as exc:  # noqa: BLE001
                        self._report(f"{type(exc).__name__}: {exc}")
            with self._cond:
                if not self._running:
                    break
                if self._reschedule:
                    self._reschedule = False
                    deadline = time.monotonic()
                if self._queue:
                    continue
                if self._paused:
                    self._cond.wait(0.1)
                    continue
                if self.realtime:
                    wait = deadline - time.monotonic()
                    if wait > 0.0:
                        self._cond.wait(wait)
                        continue
            t0 = time.monotonic()
            if self.realtime and t0 - deadline > self.period:
                self.late_steps += 1
            try:
                with self.lock:
                    advanced = float(self._step())
            except Exception as exc:  # noqa: BLE001 - report, wait a period, go on
                self._report(f"{type(exc).__name__}: {exc}")
                with self._cond:
                    self._cond.wait(min(self.period, 0.1))
                deadline = time.monotonic()
                continue
            t1 = time.monotonic()
            self._record(t0, t1, advanced)
            if self.realtime:
                deadline += self.period
                if deadline < t1 - CATCH_UP * self.period:  # far behind: move the schedule on, no burst
                    deadline = t1

    def _report(self, text: str) -> None:
        self.last_error = text
        if self._on_error is not None:
            try:
                self._on_error(text)
            except Exception:  # noqa: BLE001 - a logger failing at shutdown
                pass

    def _record(self, t0: float, t1: float, advanced: float) -> None:
        dur = t1 - t0
        with self._cond:
            self.steps += 1
            self.step_s_total += dur
            self._history.append((t0, advanced))
            self._step_s_window.append((t0, dur))
            lo = t1 - self.window_s
            while self._history and self._history[0][0] < lo:
                self._history.popleft()
            while self._step_s_window and self._step_s_window[0][0] < lo:
                self._step_s_window.popleft()

    def rates(self, now: float | None = None) -> dict:
        """Achieved steps per second and real-time factor over the last ``window_s`` (0 when
        fewer than two steps), the mean and longest step there [ms]."""
        now = time.monotonic() if now is None else now
        with self._cond:
            hist = [h for h in self._history if h[0] >= now - self.window_s]
            durs = [d for t, d in self._step_s_window if t >= now - self.window_s]
        rate = rtf = 0.0
        if len(hist) >= 2:
            span = hist[-1][0] - hist[0][0]
            if now - hist[-1][0] > 2.0 * span / (len(hist) - 1):  # stalled since: count the time up to now
                span = now - hist[0][0]
            if span > 0:
                rate = (len(hist) - 1) / span
                rtf = sum(a for _t, a in hist[1:]) / span
        return {"rate_hz": rate, "real_time_factor": rtf,
                "step_ms_mean": 1000.0 * sum(durs) / len(durs) if durs else 0.0,
                "step_ms_max": 1000.0 * max(durs) if durs else 0.0}
