"""X-ray source driver interface, its simulated twin, and the beam interlock.

Safety rule (enforced here, not in the ROS node): the beam is on only while a scan is
armed, both arms report in position (recently: a stale report counts as "not in
position"), and no e-stop is latched. Losing any condition switches the beam off at once.
The beam is also never on for longer than one exposure can take (``max_beam_on_s``), so a
controller that dies with the beam on cannot leave it on; and an e-stop disarms the scan for
good: arming while it is latched is ignored, so after a reset the scan must be armed anew.
Units: kilovolt peak (kVp), watts, seconds. :class:`SourceSettings` are the source_control
node's parameters. No ROS import.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol

from robot_ct_ros.parameters import setting, validate

__all__ = ["SourceError", "XraySource", "SimulatedXraySource", "InterlockInputs", "beam_permitted",
           "InterlockedSource", "SourceSettings"]


class SourceError(RuntimeError):
    """The source refused a command or reported a fault."""


class XraySource(Protocol):
    """What the controller needs from a source driver (real or simulated)."""

    def configure(self, kvp: float, power_w: float) -> None: ...
    def set_beam(self, on: bool, now_s: float) -> None: ...
    @property
    def beam_on(self) -> bool: ...


@dataclass
class SimulatedXraySource:
    """A micro-focus source model: 60-120 kVp, up to 150 W; counts beam-on time.

    Fault injection (as :class:`~robot_ct_ros.hardware.simulated_arm.SimulatedArm`'s ``fault``): set
    ``fault_on`` or ``fault_off`` to the exception a switch-on, or a switch-off of a beam that is on,
    raises (a ``SourceError``, or what a driver's transport raises); ``off_tries`` counts those
    switch-offs, refused ones included."""

    kvp: float = 90.0
    power_w: float = 150.0
    kvp_range: tuple[float, float] = (60.0, 120.0)
    max_power_w: float = 150.0
    _beam_on: bool = False
    beam_on_seconds: float = 0.0
    _on_since: float | None = None
    fault_on: Exception | None = None
    fault_off: Exception | None = None
    off_tries: int = 0

    def configure(self, kvp: float, power_w: float) -> None:
        if not (self.kvp_range[0] <= kvp <= self.kvp_range[1]):
            raise SourceError(f"kVp {kvp} outside {self.kvp_range}")
        if not (0.0 < power_w <= self.max_power_w):
            raise SourceError(f"power {power_w} W outside (0, {self.max_power_w}]")
        if self._beam_on:
            raise SourceError("cannot change kVp/power while the beam is on")
        self.kvp, self.power_w = float(kvp), float(power_w)

    def set_beam(self, on: bool, now_s: float) -> None:
        if on and self.fault_on is not None:
            raise self.fault_on
        if not on and self._beam_on:
            self.off_tries += 1
            if self.fault_off is not None:
                raise self.fault_off
        if on and not self._beam_on:
            self._on_since = now_s
        if not on and self._beam_on and self._on_since is not None:
            self.beam_on_seconds += now_s - self._on_since
        self._beam_on = bool(on)

    def total_beam_on_s(self, now_s: float) -> float:
        """Beam-on time so far, the current stretch included."""
        running = now_s - self._on_since if self._beam_on and self._on_since is not None else 0.0
        return self.beam_on_seconds + running

    @property
    def beam_on(self) -> bool:
        return self._beam_on


@dataclass(frozen=True)
class InterlockInputs:
    """The facts the interlock decides on; arm reports carry the time they were received."""

    scan_armed: bool = False
    source_arm_in_position: bool = False
    detector_arm_in_position: bool = False
    source_arm_stamp_s: float = float("-inf")
    detector_arm_stamp_s: float = float("-inf")
    estop_latched: bool = False


def beam_permitted(inputs: InterlockInputs, now_s: float, max_report_age_s: float) -> tuple[bool, str]:
    """Whether the beam may be on now, and the first reason it may not."""
    if inputs.estop_latched:
        return False, "e-stop latched"
    if not inputs.scan_armed:
        return False, "scan not armed"
    for name, ok, stamp in (("source arm", inputs.source_arm_in_position, inputs.source_arm_stamp_s),
                            ("detector arm", inputs.detector_arm_in_position, inputs.detector_arm_stamp_s)):
        if not ok:
            return False, f"{name} not in position"
        if now_s - stamp > max_report_age_s:
            return False, f"{name} report stale ({now_s - stamp:.2f} s old)"
    return True, "ok"


class InterlockedSource:
    """A source behind the interlock. Every input change re-evaluates and may cut the beam.

    ``request_beam(True)`` is the only way to switch the beam on; it succeeds only when
    :func:`beam_permitted` says so. ``tick(now_s)`` must be called periodically so that
    stale arm reports, and a beam on for longer than ``max_beam_on_s``, switch the beam off.
    While the e-stop is latched the scan stays disarmed whatever arrives. A switch-off the driver refuses
    (asked for or the interlock's) is retried by every ``tick`` until it succeeds, whether or not the interlock
    still permits the beam; only a permitted switch-on that succeeds cancels it. Between ticks, input changes
    (arm reports at their own rate) do not retry it, so that a slow refusing driver is asked at the tick's
    rate, not at the reports'; an e-stop retries it at once.
    """

    def __init__(self, source: XraySource, max_report_age_s: float = 1.0, max_beam_on_s: float = 10.0):
        self.source = source
        self.max_report_age_s = float(max_report_age_s)
        self.max_beam_on_s = float(max_beam_on_s)
        self.inputs = InterlockInputs()
        self.last_reason = "scan not armed"
        self.last_cut_reason = ""  # why the interlock last switched the beam off
        self.fault = ""  # the driver's last refusal or failure, kept until the same command succeeds
        self.watchdog_cut = ""  # why max_beam_on_s last cut the beam, kept until a scan is armed or the beam is on again
        self.off_pending = False  # a switch-off was asked for and refused: retried on every tick until it succeeds
        self._fault_switching_on = False
        self._on_since: float | None = None

    def _switch(self, on: bool, now_s: float) -> str:
        """Command the source; a driver fault is recorded and returned (empty when it obeyed), never raised,
        so that a refused switch-off is retried by the next tick instead of ending the controller. Any
        exception from the driver is a fault (a serial or network driver's OSError, TimeoutError...), named
        with its type where it is not a SourceError."""
        try:
            self.source.set_beam(on, now_s)
        except Exception as exc:  # noqa: BLE001 - whatever the driver raises, the beam path must go on
            what = str(exc) if isinstance(exc, SourceError) else f"{type(exc).__name__}: {exc}"
            self.fault = f"source refused beam {'on' if on else 'off'}: {what}"
            self._fault_switching_on = on
            if not on:
                self.off_pending = True
            return self.fault
        if not on:
            self.off_pending = False
        if self.fault and self._fault_switching_on == on:
            self.fault = ""
        return ""

    def _enforce(self, now_s: float, retry: bool = True) -> None:
        """Cut the beam where the inputs no longer permit it; ``retry``: also retry a refused switch-off."""
        ok, reason = beam_permitted(self.inputs, now_s, self.max_report_age_s)
        watchdog = False
        if ok and self.source.beam_on and self._on_since is not None and now_s - self._on_since > self.max_beam_on_s:
            ok, reason, watchdog = False, (f"beam on for {now_s - self._on_since:.1f} s, longer than max_beam_on_s "
                                           f"{self.max_beam_on_s:g} s: no exposure takes that long (is the scan's "
                                           "controller alive?)"), True
        self.last_reason = reason
        cut = not ok and self.source.beam_on and not (self.off_pending and not retry)
        if cut or (self.off_pending and retry):  # retried even while the interlock permits the beam
            if not self._switch(False, now_s) and cut:
                self.last_cut_reason = reason
                if watchdog:
                    self.watchdog_cut = f"beam cut: {reason}"

    def update(self, now_s: float, *, retry: bool = False, **changes) -> None:
        """Take changed inputs and re-evaluate; a refused switch-off is retried only with ``retry``."""
        inputs = replace(self.inputs, **changes)
        if inputs.estop_latched and inputs.scan_armed:
            inputs = replace(inputs, scan_armed=False)  # arming under a latched e-stop does not count, nor after
        if inputs.scan_armed and not self.inputs.scan_armed:
            self.watchdog_cut = ""  # a new scan
        self.inputs = inputs
        self._enforce(now_s, retry=retry)

    def report_arm(self, which: str, in_position: bool, now_s: float) -> None:
        if which == "source":
            self.update(now_s, source_arm_in_position=bool(in_position), source_arm_stamp_s=now_s)
        elif which == "detector":
            self.update(now_s, detector_arm_in_position=bool(in_position), detector_arm_stamp_s=now_s)
        else:
            raise ValueError(f"unknown arm {which!r}")

    def estop(self, now_s: float) -> None:
        self.update(now_s, estop_latched=True, scan_armed=False, retry=True)

    def reset_estop(self, now_s: float) -> None:
        self.update(now_s, estop_latched=False)

    def tick(self, now_s: float) -> None:
        self._enforce(now_s)

    def request_beam(self, on: bool, now_s: float) -> tuple[bool, str]:
        """Switch the beam; the answer says whether it is done, and why not (a driver fault included)."""
        if not on:
            fault = self._switch(False, now_s)
            return (False, fault) if fault else (True, "beam off")
        ok, reason = beam_permitted(self.inputs, now_s, self.max_report_age_s)
        self.last_reason = reason
        if not ok:
            return False, f"beam refused: {reason}"
        if not self.source.beam_on:
            self._on_since = now_s
        fault = self._switch(True, now_s)
        if fault:
            if self.source.beam_on and not self._switch(False, now_s):  # half done: not left on after a no
                self.fault, self._fault_switching_on = fault, True  # the switch-on fault is the one to report
            return False, f"beam refused: {fault}"
        self.watchdog_cut = ""  # a good exposure
        self.off_pending = False  # a permitted switch-on that succeeded supersedes a refused switch-off
        return True, "beam on"

    @property
    def beam_on(self) -> bool:
        return self.source.beam_on


@dataclass(frozen=True)
class SourceSettings:
    """The tube settings and the interlock's time limits (the source_control node's parameters).

    The tube range is the source's to check (:meth:`XraySource.configure` refuses what it cannot
    do, and the node's configure transition fails with the reason), so kvp and power_w are bounded
    here only by physics (>= 0; a negative value is refused as the parameter is declared).
    """

    kvp: float = setting(90.0, "tube voltage (60-120 for the simulated source)", unit="kVp", minimum=0.0)
    power_w: float = setting(150.0, "tube power (<= 150 for the simulated source)", unit="W", minimum=0.0)
    max_report_age_s: float = setting(1.0, "an arm in-position report older than this cuts the beam", unit="s",
                                      minimum=0.0)
    max_beam_on_s: float = setting(10.0, "the beam is cut when on for longer than this (keep it above the longest "
                                         "exposure)", unit="s", minimum=0.0)

    def __post_init__(self):
        validate(self)

    def interlocked(self, source: XraySource) -> InterlockedSource:
        """``source`` configured at these settings, behind the interlock; raises SourceError if it refuses."""
        source.configure(self.kvp, self.power_w)
        return InterlockedSource(source, max_report_age_s=self.max_report_age_s, max_beam_on_s=self.max_beam_on_s)
