"""Exposures of a photon-counting detector: one at a time, on a worker thread, under a deadline;
and the beam log that tells a usable frame from a beam-interrupted one (no ROS import).

:class:`ExposureGate` runs :meth:`PhotonCountingDetector.acquire` on a worker thread and waits
for the frame or the deadline, so a hanging detector never hangs its caller: the pcd_grabber's
pcd/expose service calls :meth:`ExposureGate.expose` and answers from the :class:`ExposureResult`.
A request is refused while the gate is inactive or busy, and (a detector fault) while the
previous acquisition still hangs or the detector is not connected. :meth:`ExposureGate.cancel`
answers an exposure in flight with failure and drops its frame (lifecycle deactivate).

Beam-interrupted frames (docs/bag-format.md): a frame is usable when the beam was on throughout
its exposure (a projection), or off throughout and already off at the request (a dark frame);
any other frame (the beam dropped, or came on, during the exposure: the interlock or an e-stop
cut it) is not (:func:`frame_usable`). The beam state is known by the reception times of the
source's beam reports (:class:`BeamLog`); before the first report the beam counts as off.

Times are integer nanoseconds of the owner's clock.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Callable

from robot_ct_ros.hardware.detector import DetectorError, Frame

__all__ = ["BeamLog", "frame_usable", "ExposureResult", "ExposureGate"]


class BeamLog:
    """The beam state over time, as received: ``(t_ns, on)`` at each change, thread-safe.

    Parameters
    ----------
    keep_ns : int
        History kept (default one minute), always with the state before it.
    """

    def __init__(self, keep_ns: int = 60_000_000_000):
        self.keep_ns = int(keep_ns)
        self._lock = threading.Lock()
        self._log: list[tuple[int, bool]] = []

    def record(self, t_ns: int, on: bool) -> None:
        """The beam was reported ``on`` (or off) at ``t_ns``; only changes are kept."""
        with self._lock:
            if not self._log or self._log[-1][1] != on:
                self._log.append((t_ns, bool(on)))
            while len(self._log) > 2 and self._log[1][0] < t_ns - self.keep_ns:
                self._log.pop(0)

    @property
    def entries(self) -> list[tuple[int, bool]]:
        """A copy of the log, oldest first."""
        with self._lock:
            return list(self._log)

    def fraction(self, start_ns: int, end_ns: int) -> float:
        """Fraction of [start_ns, end_ns] with the beam on (0 for an empty interval)."""
        if end_ns <= start_ns:
            return 0.0
        on_ns, state, t = 0, False, start_ns
        for t_i, s_i in self.entries:
            if t_i <= start_ns:
                state = s_i
                continue
            if t_i >= end_ns:
                break
            if state:
                on_ns += t_i - t
            t, state = t_i, s_i
        if state:
            on_ns += end_ns - t
        return on_ns / (end_ns - start_ns)

    def on_at(self, t_ns: int) -> bool:
        """The beam state at ``t_ns`` (off before the first report)."""
        states = [on for t, on in self.entries if t <= t_ns]
        return bool(states) and states[-1]


def frame_usable(beam_fraction: float, beam_on_at_request: bool) -> bool:
    """Whether a frame is a projection (beam on throughout) or a dark frame (off throughout, and
    already off when it was requested), rather than a beam-interrupted frame."""
    return beam_fraction == 1.0 or (beam_fraction == 0.0 and not beam_on_at_request)


@dataclass(frozen=True)
class ExposureResult:
    """What one exposure request came to.

    Attributes
    ----------
    frame : Frame or None
        The frame, or None when there is none (then ``problem`` says why).
    problem : str
        Why there is no frame ("" with a frame).
    fault : str
        A detector fault to count and log ("exposure refused: ..." or "exposure failed: ..."); ""
        when the request was refused for the caller's reasons (inactive, busy) or cancelled.
    requested_ns : int
        When the request started (0 if it was refused).
    crashed : bool
        The driver raised something other than a DetectorError: a bug, not a detector fault (the
        owner treats it as a dead worker: an error transition).
    """

    frame: Frame | None = None
    problem: str = ""
    fault: str = ""
    requested_ns: int = 0
    crashed: bool = False


class _Exposure:
    """One request in flight: the worker fills ``result``; ``done`` wakes the waiting caller."""

    def __init__(self, requested_ns: int):
        self.requested_ns = requested_ns
        self.done = threading.Event()
        self.result: Frame | Exception | None = None
        self.cancelled = ""     # why the owner gave up on it (deactivated, shutting down)
        self.abandoned = False  # answered already (timeout, cancel): a late frame is dropped


class ExposureGate:
    """One exposure at a time, on a worker thread, with a deadline (module docstring).

    Parameters
    ----------
    clock_ns : callable() -> int
        The owner's clock (ns).
    on_late_frame : callable(), optional
        Called from the worker when a frame arrives after its request was answered (it is dropped).
    """

    def __init__(self, clock_ns: Callable[[], int], on_late_frame: Callable[[], None] | None = None):
        self._clock_ns = clock_ns
        self._on_late_frame = on_late_frame or (lambda: None)
        self._lock = threading.Lock()
        self.active = False
        self.pending: _Exposure | None = None
        self._worker: threading.Thread | None = None

    def activate(self) -> None:
        """Serve requests from now on."""
        self.active = True

    def cancel(self, why: str) -> None:
        """Refuse requests from now on; an exposure in flight is answered failure ``why``, its frame dropped."""
        with self._lock:
            self.active = False
            pending = self.pending
            if pending is not None:
                pending.cancelled = why
        if pending is not None:
            pending.done.set()

    def join(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` for the worker (after the detector was disconnected)."""
        if self._worker is not None:
            self._worker.join(timeout_s)

    def _refusal(self, detector, state: str) -> tuple[str, bool] | None:
        """Why a request cannot start now, and whether that is a detector fault (under the lock)."""
        if not self.active:
            return f"detector not active (lifecycle state {state})", False
        if self.pending is not None:
            return "detector busy: an exposure is in progress", False
        if self._worker is not None and self._worker.is_alive():
            return "detector not responding: the previous acquisition never completed", True
        if detector is None or not detector.is_connected:
            return "detector not connected", True
        return None

    def expose(self, detector, exposure_s: float, timeout_s: float, state: str = "") -> ExposureResult:
        """Expose ``detector`` for ``exposure_s`` and wait up to ``timeout_s`` for the frame (blocking).

        Parameters
        ----------
        detector : PhotonCountingDetector or None
            The connected detector.
        exposure_s, timeout_s : float
            Exposure time and the deadline for the frame from now (s).
        state : str
            The owner's state, named in the refusal while inactive.

        Returns
        -------
        ExposureResult
        """
        with self._lock:
            refusal = self._refusal(detector, state)
            if refusal is None:
                exposure = _Exposure(self._clock_ns())
                self._worker = threading.Thread(target=self._acquire, args=(exposure, detector, exposure_s),
                                                name="pcd_acquire", daemon=True)
                self._worker.start()
                self.pending = exposure  # visible once the worker runs: "busy" means acquiring
        if refusal is not None:
            problem, fault = refusal
            return ExposureResult(problem=problem, fault=f"exposure refused: {problem}" if fault else "")

        in_time = exposure.done.wait(timeout_s)
        with self._lock:
            exposure.abandoned = True
            if self.pending is exposure:
                self.pending = None
            result, cancelled = exposure.result, exposure.cancelled
        if cancelled:
            return ExposureResult(problem=cancelled, requested_ns=exposure.requested_ns)
        if not in_time or result is None:
            problem = f"detector timeout: no frame within {timeout_s:.3g} s"
        elif isinstance(result, Exception):
            problem = f"{type(result).__name__}: {result}"
        else:
            return ExposureResult(frame=result, requested_ns=exposure.requested_ns)
        return ExposureResult(problem=problem, fault=f"exposure failed: {problem}", requested_ns=exposure.requested_ns,
                              crashed=isinstance(result, Exception) and not isinstance(result, DetectorError))

    def _acquire(self, exposure: _Exposure, detector, exposure_s: float) -> None:
        try:
            result = detector.acquire(exposure_s)
        except Exception as exc:  # DetectorError, or a bug in a driver: reported, never raised into the void
            result = exc
        with self._lock:
            exposure.result = result
            late = exposure.abandoned
        exposure.done.set()
        if late and not isinstance(result, Exception):
            self._on_late_frame()
