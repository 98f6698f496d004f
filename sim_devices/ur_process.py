"""Run the simulated cell as its own process: one `SimWorld`, the UR controller on a host address
and, optionally, the GeoCOM tracker on a pty, both reading the same world.

The ur_rtde Python constructors hold the GIL while they connect, so the controller must not live
in the client's process. Three ways to start it:

- command line: `python -m sim_devices.ur_process --host 127.0.0.2 --seed 0 --time-scale 10
  [--effects realistic] [--faults JSON] [--tracker]`. It prints one JSON line when listening:
  {"ur_host": ..., "tracker_port": "/dev/pts/N" or null, "pid": ..., "time_scale": ...}. Then it
  reads JSON commands on stdin, one a line, and answers each with one JSON line:
  {"cmd": "inject", "kind": "rtde_drop" | "protective_stop" | "restart", ...},
  {"cmd": "state"}, {"cmd": "true_tracker"}, {"cmd": "stop"}. End of stdin stops the process
  (so it never outlives a parent that talks to it) unless `--no-stdin` is given; SIGTERM / SIGINT
  stop it too.
- `SimProcess(...)` (below): starts that command as a child and talks to it (tests, `workcell sim`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable

import numpy as np

from sim_devices.truth import make_truth
from sim_devices.ur_controller import UrControllerSim
from sim_devices.world import ScaledClock, SimWorld


def build_sim(
    host: str = "127.0.0.2",
    seed: int = 0,
    effects: str | dict | None = "realistic",
    time_scale: float = 1.0,
    faults: dict | None = None,
    with_tracker: bool = False,
    *,
    robot: str = "ur5e",
    tracker_faults: dict | None = None,
    log: Callable[[str], None] | None = None,
):
    """-> (world, controller, tracker or None), all started. Every setting (fault settings
    included) is checked before anything listens: a bad one raises ValueError and leaves no
    port open."""
    if with_tracker:
        try:
            from sim_devices.geocom_tracker import SimGeoComTracker, validate_faults
        except ImportError as e:  # pragma: no cover - depends on the other engineer's module
            raise RuntimeError(f"simulated tracker not available: {e}") from None
        validate_faults(tracker_faults)
    truth = make_truth(robot, effects, seed)
    world = SimWorld(truth, clock=ScaledClock(time_scale), seed=seed)
    ctrl = UrControllerSim(world, host, time_scale=time_scale, faults=faults, seed=seed, log=log)
    ctrl.start()
    tracker = None
    if with_tracker:
        try:
            # the same clock as the world's: a simulated delay d takes d / time_scale wall
            # seconds (until 2026-11-26 it got 1 / time_scale: d * time_scale wall seconds)
            tracker = SimGeoComTracker(
                world.read_tracker, faults=tracker_faults, seed=seed, time_scale=time_scale
            )
            tracker.start()
        except BaseException:
            ctrl.stop()
            raise
    return world, ctrl, tracker


def _info(ctrl: UrControllerSim, tracker) -> dict:
    return {
        "ur_host": ctrl.host,
        "tracker_port": None if tracker is None else tracker.port,
        "pid": os.getpid(),
        "time_scale": ctrl.time_scale,
    }


def _state(world: SimWorld, ctrl: UrControllerSim) -> dict:
    q, qd = world.joint_state()
    with ctrl.lock:
        return {
            "t_s": world.clock.now(),
            "q_rad": q.tolist(),
            "qd_rad_s": qd.tolist(),
            "robot_mode": ctrl.robot_mode,
            "safety_mode": ctrl.safety_mode,
            "runtime_state": ctrl.runtime_state,
            "moves": ctrl.move_count,
            "stats": dict(ctrl.stats),
            "events": [list(e) for e in ctrl.events[-50:]],
        }


def _handle(cmd: dict, world: SimWorld, ctrl: UrControllerSim) -> dict:
    c = cmd.get("cmd")
    if c == "inject":
        kw = {k: v for k, v in cmd.items() if k not in ("cmd", "kind")}
        ctrl.inject(str(cmd.get("kind")), **kw)
        return {"ok": True}
    if c == "state":
        return {"ok": True, **_state(world, ctrl)}
    if c == "true_tracker":
        return {"ok": True, "p_tracker": np.asarray(world.true_smr_tracker()).tolist()}
    if c == "stop":
        return {"ok": True, "stopping": True}
    return {"ok": False, "error": f"unknown command {c!r}"}


def run_sim(
    host: str = "127.0.0.2",
    seed: int = 0,
    effects: str | dict | None = "realistic",
    time_scale: float = 1.0,
    faults: dict | None = None,
    with_tracker: bool = False,
    *,
    robot: str = "ur5e",
    ready: Callable[[dict], None] | None = None,
    commands=None,
    replies=None,
    stop_event: threading.Event | None = None,
    verbose: bool = False,
    tracker_faults: dict | None = None,
) -> int:
    """Host the world, the controller and optionally the tracker until told to stop.

    `ready(info)` is called once listening. `commands` (a text stream) yields JSON command lines,
    answered on `replies`; its end stops the sim. Without `commands`, runs until `stop_event` is
    set or SIGTERM/SIGINT.
    """
    log = (lambda m: print(m, file=sys.stderr, flush=True)) if verbose else None
    world, ctrl, tracker = build_sim(
        host,
        seed,
        effects,
        time_scale,
        faults,
        with_tracker,
        robot=robot,
        log=log,
        tracker_faults=tracker_faults,
    )
    stop = stop_event or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    try:
        if ready is not None:
            ready(_info(ctrl, tracker))
        if commands is None:
            while not stop.wait(0.2):
                pass
            return 0

        def reader() -> None:
            for line in commands:
                line = line.strip()
                if not line:
                    continue
                try:
                    ans = _handle(json.loads(line), world, ctrl)
                except Exception as e:  # bad command: answer, keep running
                    ans = {"ok": False, "error": str(e)}
                if replies is not None:
                    replies.write(json.dumps(ans) + "\n")
                    replies.flush()
                if ans.get("stopping"):
                    break
            stop.set()

        threading.Thread(target=reader, name="ur-sim-stdin", daemon=True).start()
        while not stop.wait(0.2):
            pass
        return 0
    finally:
        if tracker is not None:
            tracker.stop()
        ctrl.stop()


# ------------------------------------------------------------------ parent side
class SimProcess:
    """Start `python -m sim_devices.ur_process` as a child; always `stop()` it (or use `with`)."""

    def __init__(
        self,
        host: str = "127.0.0.2",
        *,
        seed: int = 0,
        effects: str = "realistic",
        time_scale: float = 1.0,
        faults: dict | None = None,
        with_tracker: bool = False,
        robot: str = "ur5e",
        startup_timeout_s: float = 30.0,
        tracker_faults: dict | None = None,
        verbose: bool = False,
    ) -> None:
        self.args = [
            sys.executable,
            "-m",
            "sim_devices.ur_process",
            "--host",
            host,
            "--seed",
            str(seed),
            "--effects",
            effects,
            "--time-scale",
            str(time_scale),
            "--robot",
            robot,
        ]
        if faults:
            self.args += ["--faults", json.dumps(faults)]
        if with_tracker:
            self.args.append("--tracker")
        if tracker_faults:
            self.args += ["--tracker-faults", json.dumps(tracker_faults)]
        if verbose:
            self.args.append("--verbose")
        self.startup_timeout_s = startup_timeout_s
        self.proc: subprocess.Popen | None = None
        self.info: dict = {}
        self._lock = threading.Lock()

    def start(self) -> SimProcess:
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env = dict(os.environ)
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
        self.proc = subprocess.Popen(
            self.args,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=None,
            text=True,
            bufsize=1,
            env=env,
        )
        box: dict = {}

        def read_ready() -> None:
            box["line"] = self.proc.stdout.readline()

        t = threading.Thread(target=read_ready, daemon=True)
        t.start()
        t.join(self.startup_timeout_s)
        line = box.get("line", "")
        if not line:
            rc = self.proc.poll()
            self.stop()
            raise RuntimeError(
                f"simulated UR controller did not start (exit code {rc}); "
                f"command: {' '.join(self.args)}"
            )
        self.info = json.loads(line)
        return self

    @property
    def pid(self) -> int:
        return self.proc.pid if self.proc else -1

    def command(self, cmd: dict, timeout_s: float = 10.0) -> dict:
        if self.proc is None or self.proc.poll() is not None:
            raise RuntimeError("simulated UR controller process is not running")
        with self._lock:
            self.proc.stdin.write(json.dumps(cmd) + "\n")
            self.proc.stdin.flush()
            box: dict = {}
            t = threading.Thread(
                target=lambda: box.setdefault("l", self.proc.stdout.readline()), daemon=True
            )
            t.start()
            t.join(timeout_s)
            if "l" not in box or not box["l"]:
                raise RuntimeError(f"no answer from the simulated controller to {cmd}")
            return json.loads(box["l"])

    def inject(self, kind: str, **kw) -> dict:
        return self.command({"cmd": "inject", "kind": kind, **kw})

    def state(self) -> dict:
        return self.command({"cmd": "state"})

    def stop(self, timeout_s: float = 5.0) -> None:
        p = self.proc
        if p is None:
            return
        if p.poll() is None:
            with contextlib.suppress(OSError, ValueError):
                p.stdin.close()  # end of stdin: the child stops itself
            try:
                p.wait(timeout_s)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout_s)
        for s in (p.stdin, p.stdout):
            with contextlib.suppress(OSError, ValueError):
                if s is not None:
                    s.close()
        self.proc = None

    def __enter__(self) -> SimProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


# ------------------------------------------------------------------ command line
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m sim_devices.ur_process",
        description="Simulated UR controller (+ GeoCOM tracker) process.",
    )
    ap.add_argument("--host", default="127.0.0.2", help="address to listen on (loopback alias)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--effects",
        default="realistic",
        help="none, realistic, all, or a comma list of effect kinds",
    )
    ap.add_argument(
        "--time-scale", type=float, default=1.0, help="simulated seconds per wall second"
    )
    ap.add_argument("--faults", default=None, help="JSON dict of controller faults")
    ap.add_argument("--tracker-faults", default=None, help="JSON dict of tracker faults")
    ap.add_argument("--robot", default="ur5e")
    ap.add_argument("--tracker", action="store_true", help="also serve a GeoCOM tracker on a pty")
    ap.add_argument(
        "--no-stdin", action="store_true", help="ignore stdin; run until SIGTERM/SIGINT"
    )
    ap.add_argument("--verbose", action="store_true", help="log controller events on stderr")
    a = ap.parse_args(argv)
    try:
        faults = json.loads(a.faults) if a.faults else None
        tfaults = json.loads(a.tracker_faults) if a.tracker_faults else None
    except json.JSONDecodeError as e:
        print(f"--faults/--tracker-faults: not valid JSON ({e})", file=sys.stderr)
        return 2

    def announce(info: dict) -> None:
        print(json.dumps(info), flush=True)

    try:
        return run_sim(
            a.host,
            a.seed,
            a.effects,
            a.time_scale,
            faults,
            a.tracker,
            robot=a.robot,
            ready=announce,
            commands=None if a.no_stdin else sys.stdin,
            replies=sys.stdout,
            verbose=a.verbose,
            tracker_faults=tfaults,
        )
    except (OSError, ValueError, RuntimeError) as e:
        print(f"ur_process: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
