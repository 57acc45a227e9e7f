"""Child-process side of :class:`robot_ct_ros.hardware.ur_arm.URArm`: owns the ur-rtde objects.

Started by the parent with the multiprocessing ``spawn`` context; talks over one duplex pipe.
Requests are ``(id, op, args)``; replies ``(id, status, payload)`` with status ``"ok"`` (payload:
the result) or ``"error"`` (payload: ``(kind, message)``, kind one of ``"connection"``,
``"motion"``, ``"other"``). While connecting, the worker also sends progress notes
``(id, "progress", stage)`` (stage :data:`TCP_ACCEPTED`, then :data:`RTDE_RECEIVING`) so that the
parent, timing out, can say how far the controller got. Moves run on their own thread (the ur-rtde
bindings release the GIL there), so state reads keep being answered during a move. The parent enforces every timeout and
kills this process when the controller stops answering; nothing here needs to be interruptible.
"""

from __future__ import annotations

import os
import signal
import socket
import sys
import threading

__all__ = ["STATE_VARIABLES", "RTDE_PORT", "TCP_ACCEPTED", "RTDE_RECEIVING", "worker_main"]

STATE_VARIABLES = ["timestamp", "actual_q", "actual_TCP_pose", "robot_mode", "safety_mode", "runtime_state"]
RTDE_PORT = 30004
TCP_ACCEPTED = "tcp_accepted"      # the controller accepted a TCP connection on the RTDE port
RTDE_RECEIVING = "rtde_receiving"  # the RTDE receive interface is up (handshake done); the control one is next


class _Worker:
    def __init__(self, conn, host: str):
        self.conn = conn
        self.host = host
        self.send_lock = threading.Lock()
        self.receive = None
        self.control = None
        self.move_lock = threading.Lock()

    def reply(self, msg_id, status, payload=None) -> None:
        with self.send_lock:
            try:
                self.conn.send((msg_id, status, payload))
            except (OSError, ValueError, BrokenPipeError):
                pass

    def tcp_accepts(self, timeout_s: float) -> bool:
        """Whether the controller accepts a TCP connection on the RTDE port (closed at once). ur-rtde's
        constructors, stuck on a peer that accepts but never completes the RTDE handshake, hold the GIL,
        so this is the only way to tell the parent that much before they run."""
        try:
            socket.create_connection((self.host, RTDE_PORT), timeout=timeout_s).close()
            return True
        except OSError:
            return False

    def connect(self, options: dict, msg_id=None) -> dict:
        import rtde_control
        import rtde_receive

        freq = float(options.get("frequency", -1.0))
        if msg_id is not None and self.tcp_accepts(float(options.get("timeout_s", 10.0))):
            self.reply(msg_id, "progress", TCP_ACCEPTED)
        # Receive first: its constructor is the one that blocks on a silent peer (the parent
        # times out and kills us); the control interface then uploads its script.
        self.receive = rtde_receive.RTDEReceiveInterface(self.host, freq, STATE_VARIABLES)
        if msg_id is not None:
            self.reply(msg_id, "progress", RTDE_RECEIVING)
        flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        if options.get("verbose"):
            flags |= rtde_control.RTDEControlInterface.FLAG_VERBOSE
        self.control = rtde_control.RTDEControlInterface(self.host, freq, flags)
        return {"program_running": bool(self.control.isProgramRunning()),
                "robot_mode": int(self.receive.getRobotMode())}

    def state(self) -> dict:
        r = self.receive
        connected = bool(r.isConnected()) and bool(self.control.isConnected())
        return {"connected": connected,
                "tcp_pose": list(r.getActualTCPPose()),
                "joint_positions": list(r.getActualQ()),
                "timestamp": float(r.getTimestamp()),
                "robot_mode": int(r.getRobotMode()),
                "safety_mode": int(r.getSafetyMode()),
                "runtime_state": int(r.getRuntimeState())}

    def _why_refused(self, what: str) -> tuple[str, str]:
        if not self._connected():
            return "connection", f"{what} failed: RTDE connection lost"
        try:
            running = bool(self.control.isProgramRunning())
            mode, safety = int(self.receive.getRobotMode()), int(self.receive.getSafetyMode())
        except Exception as exc:  # noqa: BLE001
            return "connection", f"{what} failed: {exc}"
        return "motion", (f"{what} refused by the controller (control script running: {running}, "
                          f"robot_mode {mode}, safety_mode {safety})")

    def _connected(self) -> bool:
        try:
            return bool(self.receive.isConnected()) and bool(self.control.isConnected())
        except Exception:  # noqa: BLE001
            return False

    def move(self, msg_id, op: str, args) -> None:
        """Run a blocking ur-rtde move on an inner thread; give up at once if the link drops.

        ur-rtde's own wait for the script's "done" signal only ends on its 300 s execution
        timeout when the controller vanishes, so the link is watched here; the parent then
        kills this process (the stuck library thread with it).
        """
        target, speed, accel = args
        result: dict = {}

        def run():
            try:
                fn = self.control.moveL if op == "moveL" else self.control.moveJ
                result["ok"] = bool(fn(list(target), speed, accel, False))
            except Exception as exc:  # noqa: BLE001
                result["error"] = f"{op} raised: {exc}"

        with self.move_lock:
            inner = threading.Thread(target=run, daemon=True)
            inner.start()
            while inner.is_alive():
                inner.join(0.05)
                if inner.is_alive() and not self._connected():
                    self.reply(msg_id, "error", ("connection", f"{op} interrupted: RTDE connection lost"))
                    return
        if "error" in result:
            self.reply(msg_id, "error", ("motion", result["error"]))
        elif result.get("ok"):
            self.reply(msg_id, "ok", None)
        else:
            self.reply(msg_id, "error", self._why_refused(op))

    def disconnect(self) -> None:
        for obj in (self.control, self.receive):
            if obj is None:
                continue
            try:
                if obj is self.control and obj.isConnected():
                    obj.stopScript()
                obj.disconnect()
            except Exception:  # noqa: BLE001
                pass

    def serve(self) -> None:
        while True:
            try:
                msg_id, op, args = self.conn.recv()
            except (EOFError, OSError):
                return
            try:
                if op == "connect":
                    self.reply(msg_id, "ok", self.connect(*args, msg_id=msg_id))
                elif op in ("moveL", "moveJ"):
                    threading.Thread(target=self.move, args=(msg_id, op, args), daemon=True).start()
                elif op == "state":
                    self.reply(msg_id, "ok", self.state())
                elif op == "disconnect":
                    self.disconnect()
                    self.reply(msg_id, "ok", None)
                    return
                else:
                    self.reply(msg_id, "error", ("other", f"unknown request {op!r}"))
            except RuntimeError as exc:
                kind = "connection" if op in ("connect", "state") else "other"
                self.reply(msg_id, "error", (kind, str(exc)))
            except Exception as exc:  # noqa: BLE001
                self.reply(msg_id, "error", ("other", f"{type(exc).__name__}: {exc}"))


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def die_with_parent(parent_pid: int | None) -> bool:
    """On Linux, have the kernel SIGKILL this process when its parent dies, and leave at once if it
    already has (it may have died before the request was made). Returns whether the request was made.

    A closed pipe ends this process only while it can run Python: ur-rtde's constructors, stuck on
    a silent controller, hold the GIL, so a parent killed then (SIGKILL: no cleanup of its own)
    would leave this process behind for good. The signal comes when the parent's *thread* that
    started this process ends: URArm starts it from a thread that lives as long as the parent.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) != 0:
            return False
    except (OSError, AttributeError):
        return False
    if parent_pid is not None and os.getppid() != parent_pid:  # the parent died before the request
        os._exit(1)
    return True


def worker_main(conn, host: str, parent_pid: int | None = None) -> None:
    """Entry point of the child process.

    The process dies with its parent (:func:`die_with_parent`). SIGINT is ignored (Ctrl-C reaches
    the whole process group; the parent decides when this process ends: a "disconnect" request, a
    closed pipe, or a kill). The process leaves with os._exit so that no library destructor can
    block the exit on a stuck connection.
    """
    die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    worker = _Worker(conn, host)
    try:
        worker.serve()
    finally:
        try:
            conn.close()
        except OSError:
            pass
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
