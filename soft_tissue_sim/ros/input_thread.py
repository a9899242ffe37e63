"""Subscriptions served by a thread of their own instead of an executor.

An rclpy executor rebuilds its wait set from every entity of its nodes (services, parameter
services, timers...) on every wake-up and hands each message through Python machinery: about
half a millisecond of CPU per message, most of a core at 1 kHz of instrument poses, all of it
holding the GIL the physics thread needs. Here the instrument subscriptions belong to a
callback group no executor runs (:class:`ThreadServedGroup`), and :class:`InputThread` waits on
just them (rclpy's wait set, the GIL released while waiting), takes each ready message and
calls the subscription's callback, in the order the subscriptions were given. The same wait
set and take calls as :func:`rclpy.wait_for_message.wait_for_message`. :meth:`InputThread.drain`
takes, from the calling thread, what has arrived and not been taken yet (a request that must see
the newest pose); takes and callbacks are serialized, so messages keep their order.
"""

from __future__ import annotations

import threading

from rclpy.callback_groups import CallbackGroup
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy


class ThreadServedGroup(CallbackGroup):
    """A callback group whose entities no executor takes: a thread of their own serves them."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


class InputThread:
    """Serve ``subscriptions`` (created in a :class:`ThreadServedGroup`) from one thread.
    ``on_error(text)`` hears about a callback that raised (the thread goes on)."""

    def __init__(self, context, subscriptions, name: str = "input", on_error=None):
        self._context = context
        self._subs = list(subscriptions)
        self._on_error = on_error
        self._running = False
        self._wake = GuardCondition(None, None, context=context)
        self._take_lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        if not self._running and self._subs:
            self._running = True
            self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        if not self._running:
            return
        self._running = False
        try:
            self._wake.trigger()
        except Exception:  # noqa: BLE001 - context already shut down: the wait returns anyway
            pass
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def _run(self) -> None:
        try:
            ws = _rclpy.WaitSet(len(self._subs), 1, 0, 0, 0, 0, self._context.handle)
        except Exception as exc:  # noqa: BLE001
            self._report(f"input thread cannot start: {exc}")
            return
        while self._running and self._context.ok():
            try:
                ws.clear_entities()
                for s in self._subs:
                    ws.add_subscription(s.handle)
                ws.add_guard_condition(self._wake.handle)
                ws.wait(100_000_000)  # 0.1 s: also notices a shut-down context
                ready = ws.get_ready_entities("subscription")
            except Exception as exc:  # noqa: BLE001 - the context or a handle went away
                if self._running and self._context.ok():
                    self._report(f"input wait failed: {type(exc).__name__}: {exc}")
                break
            for s in self._subs:
                if ready and s.handle.pointer in ready:
                    self._take(s)

    def drain(self) -> None:
        """Take and handle every message that has arrived (from the calling thread)."""
        for s in self._subs:
            while self._take(s):
                pass

    def _take(self, s) -> bool:
        """Take one message of subscription ``s`` and run its callback; whether there was one."""
        with self._take_lock:
            try:
                with s.handle:
                    info = s.handle.take_message(s.msg_type, s.raw)
                if info is None:
                    return False
                s.callback(info[0])
            except Exception as exc:  # noqa: BLE001 - one bad message never stops the input
                self._report(f"input callback failed: {type(exc).__name__}: {exc}")
                return False
            return True

    def _report(self, text: str) -> None:
        if self._on_error is not None:
            try:
                self._on_error(text)
            except Exception:  # noqa: BLE001
                pass
