"""Connecting and disconnecting an arm off the caller's thread (no ROS import).

A controller that is slow to answer (or never answers) must not stall the caller, e.g. the
executor of the arm_driver node: :class:`BackgroundConnection` runs ``connect()`` on a daemon
thread, keeps the result of the newest attempt, and calls ``notify()`` (the node wires it to a
guard condition's ``trigger``) so that the caller collects it on its own thread with
:meth:`BackgroundConnection.take`, which keeps a connected arm as ``arm``. Abandoning an attempt
(:meth:`BackgroundConnection.abandon`) makes any result still to come stale: the connect thread
then discards it and disconnects its arm there. :meth:`BackgroundConnection.release` disconnects
a connected arm on a thread too (a hung controller's disconnect takes its timeout);
:meth:`BackgroundConnection.disconnect` abandons and releases; :meth:`BackgroundConnection.close`
waits for those disconnects.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

from robot_ct_ros.hardware.arm import ArmError

__all__ = ["BackgroundConnection", "quiet_disconnect"]


def quiet_disconnect(arm, warn: Callable[[str], None] | None = None) -> None:
    """``arm.disconnect()``, never raising: a failure is passed to ``warn`` (if given) as "disconnect: ..."."""
    try:
        arm.disconnect()
    except Exception as exc:  # noqa: BLE001 - letting go of an arm never fails the caller
        if warn is not None:
            warn(f"disconnect: {exc}")


def connect_error(exc: BaseException) -> str:
    """How a failed ``connect()`` is reported: the message of an ArmError or OSError, else type and message."""
    return str(exc) if isinstance(exc, (ArmError, OSError)) else f"{type(exc).__name__}: {exc}"


class BackgroundConnection:
    """Connection attempts on background threads, their results handed to the caller's thread.

    Parameters
    ----------
    notify : callable
        Called (no arguments, on the connect thread) when the current attempt has a result to
        :meth:`take`; if it raises (the owner is being destroyed), the arm is disconnected there.
    warn : callable, optional
        Told (one string) when a :meth:`release` disconnect fails.
    name : str
        Prefix of the thread names (``<name>_connect``, ``<name>_disconnect``).
    """

    def __init__(self, notify: Callable[[], None], warn: Callable[[str], None] | None = None, name: str = "arm"):
        self._notify, self._warn, self._name = notify, warn, name
        self._lock = threading.Lock()
        self._attempt = 0  # a result of an older attempt is discarded
        self._result = None
        self._release_threads: list[threading.Thread] = []
        self.connecting = False  # an attempt is under way (or its result not yet taken)
        self.arm = None  # the connected arm: taken from a successful attempt, until disconnect()
        self.started_s = 0.0  # time.monotonic() when the current attempt started

    @property
    def elapsed_s(self) -> float:
        """Seconds since the current (or last) attempt started."""
        return time.monotonic() - self.started_s

    def start(self, arm) -> threading.Thread:
        """Connect ``arm`` on a new thread; this attempt supersedes any earlier one."""
        with self._lock:
            self._attempt += 1
            attempt = self._attempt
            self.connecting, self.started_s = True, time.monotonic()
        t = threading.Thread(target=self._connect, args=(arm, attempt), name=f"{self._name}_connect", daemon=True)
        t.start()
        return t

    def _connect(self, arm, attempt: int) -> None:
        try:
            arm.connect()
            error = None
        except Exception as exc:  # noqa: BLE001 - ArmError, OSError, or a driver bug: all reported
            error = connect_error(exc)
        with self._lock:
            current = attempt == self._attempt
            if current:
                self._result = (attempt, arm, error)
        if not current:  # abandoned meanwhile (cleanup, shutdown): let go of it here, off the caller's thread
            if error is None:
                quiet_disconnect(arm)
            return
        try:
            self._notify()
        except Exception:  # noqa: BLE001 - the owner is being destroyed
            quiet_disconnect(arm)

    def take(self):
        """``(arm, error)`` of the current attempt once it has ended (error None: connected, and the
        arm is kept as :attr:`arm`; else why not), and the attempt is over; None when there is
        nothing (yet), or only a stale result."""
        with self._lock:
            result, self._result = self._result, None
            if result is None or result[0] != self._attempt:
                return None
            self.connecting = False
        if result[2] is None:
            self.arm = result[1]
        return result[1], result[2]

    def abandon(self) -> None:
        """Stop waiting for the attempt under way: its arm is disconnected by its own thread if it connects."""
        with self._lock:
            self._attempt += 1
            self.connecting, self._result = False, None

    def disconnect(self) -> None:
        """:meth:`abandon` any attempt under way and :meth:`release` the connected arm (if any)."""
        self.abandon()  # a connect still under way cleans up after itself
        arm, self.arm = self.arm, None
        if arm is not None:
            self.release(arm)

    def release(self, arm) -> None:
        """Disconnect ``arm`` on a background thread (failures go to ``warn``); :meth:`close` waits for it."""
        t = threading.Thread(target=quiet_disconnect, args=(arm, self._warn), name=f"{self._name}_disconnect",
                             daemon=True)
        t.start()
        self._release_threads = [x for x in self._release_threads if x.is_alive()] + [t]

    def close(self, timeout_s: float = 5.0) -> None:
        """Wait (up to ``timeout_s`` each) for the disconnects :meth:`release` started."""
        for t in self._release_threads:
            t.join(timeout_s)
