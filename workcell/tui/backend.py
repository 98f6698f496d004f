"""What the terminal UI calls: thin, UI-free wrappers over the campaign, estimation and export
packages. Everything here may block (device I/O, fitting); the app runs it in thread workers.

Nothing here re-implements calibration logic; it opens devices, builds the arguments the library
functions take and turns their results into plain dicts for the screens.
"""

from __future__ import annotations

import argparse
import importlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from workcell.drivers.protocols import close_quietly
from workcell.errors import UserError, check_output_path


class Unavailable(UserError):
    """A feature whose module is not in this build (yet)."""


# ----------------------------------------------------------------------------- devices
@dataclass
class DeviceConfig:
    robot: str = "sim"  # sim (in-process) or ur://HOST
    tracker: str = "sim"  # sim or serial:///dev/ttyX
    model: str = "ur5e"
    effects: str = "realistic"
    seed: int = 0
    time_scale: float = 1.0
    start_sim: bool = False  # start the protocol-level simulators and connect to them
    sim_host: str = "127.0.0.2"
    sim_faults: dict | None = None  # robot faults for the simulated controller
    sim_tracker_faults: dict | None = None
    smr_offset: str = ""  # 'X,Y,Z' m on the flange; '' = the default (0, 0, 0.06)
    payload: str = ""  # 'KG[,CX,CY,CZ]'; '' = not declared (the simulated arm's own in simulation)


class Held:
    """A device the app keeps open between runs. A run closes the devices it is given when it
    ends (`run_campaign`, the closed-loop check), as the command line's process ends; the app
    keeps them as the operator connected them on the Devices screen, so that its status poll
    still reads the robot's mode and safety state (the protective stop a run ended in) and the
    tracker's connection. So `close()` from a run only marks the device, and the next run's
    `connect()` closes it first, as after the run it would have been (a connection a fault
    broke is made afresh). Everything else goes to the driver; `release()` closes it
    (`Devices.close`: disconnect, reconnect, quit)."""

    __slots__ = ("_device", "_closed_by_run")

    def __init__(self, device) -> None:
        object.__setattr__(self, "_device", device)
        object.__setattr__(self, "_closed_by_run", False)

    def __getattr__(self, name: str):
        return getattr(object.__getattribute__(self, "_device"), name)

    def __setattr__(self, name: str, value) -> None:  # a run's abort flag etc.: the driver's
        setattr(self._device, name, value)

    def __repr__(self) -> str:
        return f"Held({self._device!r})"

    def connect(self) -> None:
        if self._closed_by_run:
            object.__setattr__(self, "_closed_by_run", False)
            close_quietly(self._device)
        self._device.connect()

    def close(self) -> None:
        object.__setattr__(self, "_closed_by_run", True)

    def release(self) -> None:
        self._device.close()


def _release(*devices) -> None:
    """Close each device for good (`Held.release`; a device wrapped around one forwards it),
    best effort."""
    for d in devices:
        try:
            getattr(d, "release", d.close)()
        except Exception:  # noqa: BLE001 - closing is best effort
            pass


@dataclass
class Devices:
    """An open cell: what `workcell.campaign.devices.open_cell` returns, plus bookkeeping. The
    robot and tracker are `Held`: a run leaves them open; `close()` closes them."""

    cell: object  # CellSetup
    robot: object
    tracker: object
    envelope: object
    robot_url: str
    tracker_url: str
    kind: str  # "in-process simulation", "protocol simulators", "hardware"
    config: DeviceConfig
    sim_process: object | None = None  # sim_devices.ur_process.SimProcess when we started it
    notes: list[str] = field(default_factory=list)

    def close(self) -> None:
        _release(self.robot, self.tracker)
        if self.sim_process is not None:
            try:
                self.sim_process.stop()
            except Exception:  # noqa: BLE001
                pass
            self.sim_process = None


def _namespace(cfg: DeviceConfig, robot: str, tracker: str) -> argparse.Namespace:
    return argparse.Namespace(
        robot=robot,
        tracker=tracker,
        model=cfg.model,
        effects=cfg.effects,
        seed=cfg.seed,
        time_scale=cfg.time_scale,
        smr_offset=cfg.smr_offset,
        payload=cfg.payload,
    )


TUI_PAYLOAD_HOW = "Payload on the Devices screen (kg[,CX,CY,CZ]), then connect again"


def open_devices(cfg: DeviceConfig) -> Devices:
    """Open (and connect) the devices. With `start_sim`, start the protocol simulators first
    (`sim_devices.ur_process.SimProcess`); without that module, fall back on the in-process
    simulation and say so in `notes`."""
    from workcell.campaign.devices import open_cell

    notes: list[str] = []
    robot_url, tracker_url = cfg.robot, cfg.tracker
    proc = None
    if cfg.start_sim:
        try:
            from sim_devices.ur_process import SimProcess
        except ModuleNotFoundError:
            SimProcess = None  # noqa: N806
        if SimProcess is None:
            notes.append("protocol simulators not available; using the in-process simulation")
            robot_url = tracker_url = "sim"
        else:
            proc = SimProcess(
                cfg.sim_host,
                seed=cfg.seed,
                effects=cfg.effects,
                time_scale=cfg.time_scale,
                faults=cfg.sim_faults,
                with_tracker=True,
                robot=cfg.model,
                tracker_faults=cfg.sim_tracker_faults,
            )
            try:
                proc.start()
            except (RuntimeError, OSError) as e:
                raise UserError(f"could not start the simulators: {e}") from None
            robot_url = f"ur://{proc.info['ur_host']}"
            tracker_url = f"serial://{proc.info['tracker_port']}"
    try:
        cell, robot, tracker, env = open_cell(_namespace(cfg, robot_url, tracker_url))
        robot.connect()
        tracker.connect()
    except Exception:
        if proc is not None:
            proc.stop()
        raise
    kind = (
        "in-process simulation"
        if robot_url == "sim"
        else ("protocol simulators" if proc is not None else "hardware")
    )
    from workcell.campaign.payload import settle_payload

    # the controller's payload setting against the Payload field (each campaign checks again)
    for n in settle_payload(cell, robot, how=TUI_PAYLOAD_HOW):
        notes.append(n["message"])
    return Devices(
        cell, Held(robot), Held(tracker), env, robot_url, tracker_url, kind, cfg, proc, notes
    )


def probe(dev: Devices) -> dict:
    """One status snapshot: robot mode and safety, joints, tracker connection. Never raises."""
    out: dict = {"robot": dev.robot_url, "tracker": dev.tracker_url, "kind": dev.kind}
    try:
        st = dev.robot.state()
        out.update(
            robot_ok=True,
            robot_mode=st.mode,
            safety=st.safety,
            q_rad=np.asarray(st.q_rad, float).tolist(),
        )
    except Exception as e:  # noqa: BLE001 - a status poll reports, it does not fail
        out.update(robot_ok=False, robot_mode="UNREACHABLE", safety="?", robot_error=str(e))
    conn = getattr(dev.tracker, "is_connected", None)
    if conn is None:
        conn = getattr(dev.tracker, "connected", None)
    out["tracker_ok"] = bool(conn) if conn is not None else True
    out["tracker_status"] = "connected" if out["tracker_ok"] else "disconnected"
    out["tracker_model"] = getattr(dev.cell, "tracker_model", "?")
    return out


# ----------------------------------------------------------------------------- plan
@dataclass
class PlanConfig:
    kind: str = "random"
    poses: int = 10
    seed: int = 0
    settle_s: float = 1.0
    readings_per_pose: int = 5
    envelope: str = "default"  # or a JSON file written by Envelope.to_dict
    out: str = "campaign.mcap"
    warmup_s: float = 0.0
    reference_every: int = 0  # > 0: the first pose measured again after every N poses

    def measurements(self) -> int:
        """Poses plus the reference pose's repeats (`plans.reference_repeats`)."""
        from workcell.campaign.plans import reference_repeats

        return self.poses + reference_repeats(self.poses, self.reference_every)

    def validate(self) -> None:
        from workcell.campaign.plans import MAX_POSES, PLAN_CHOICES, PLAN_KINDS

        if self.kind not in PLAN_KINDS:
            raise UserError(f"plan type {self.kind!r}: choose {PLAN_CHOICES}")
        if self.poses <= 0:
            raise UserError(f"number of poses must be positive, got {self.poses}")
        if self.poses > MAX_POSES:
            raise UserError(
                f"{self.poses} poses is more than a campaign can measure (limit {MAX_POSES}); "
                "split it into several recordings"
            )
        if self.seed < 0:
            raise UserError(f"seed must be >= 0, got {self.seed}")
        if self.readings_per_pose <= 0:
            raise UserError(f"readings per pose must be positive, got {self.readings_per_pose}")
        if self.reference_every < 0:
            raise UserError(
                f"reference interval must be a number of poses (0: none), got {self.reference_every}"
            )
        if not self.settle_s >= 0:
            raise UserError(f"settle time must be >= 0 s, got {self.settle_s}")
        if not self.out:
            raise UserError("give a recording path (.mcap)")


def envelope_for(plan: PlanConfig, dev: Devices):
    if plan.envelope in ("", "default"):
        return dev.envelope
    from workcell.campaign.envelope import load_envelope

    return load_envelope(plan.envelope, dev.cell.spec)


def campaign_config(plan: PlanConfig, dev: Devices):
    from workcell.campaign.executor import CampaignConfig

    return CampaignConfig(
        readings_per_pose=plan.readings_per_pose,
        settle_s=plan.settle_s,
        payload_kg=dev.cell.payload_kg,
        warmup_s=plan.warmup_s,
    )


def dry_run(plan: PlanConfig, dev: Devices, *, preview: bool = True) -> dict:
    """Check every planned target and pre-pose against the envelope; nothing moves. With
    `preview`, a design plan (dopt, vopt) is previewed at the nominal chain (seconds for
    tens of poses) and the expected fit is given for other pose counts; the campaign's own check
    before it starts does without (each adaptive pose is checked before it moves)."""
    from workcell.campaign.executor import PREVIEW_KINDS, dry_run_plan, preview_adaptive_plan
    from workcell.campaign.identification import (
        identification_lines,
        pose_count_warnings,
        reference_poses,
    )

    plan.validate()
    env = envelope_for(plan, dev)
    cfg = campaign_config(plan, dev)
    cell = dev.cell
    targets, problems = dry_run_plan(
        plan.kind, cell.spec, env, plan.poses, seed=plan.seed, tool_m=cell.tool_m, config=cfg
    )
    if targets is None:
        out = {"adaptive": True, "targets": plan.poses, "problems": [], "ok": True}
        if not preview:
            return out
        if plan.kind not in PREVIEW_KINDS:  # bo: its poses cannot be listed; what needs none
            return {**out, "identification": pose_count_warnings(
                cell.spec, env, cell.tool_m, plan.poses)}  # fmt: skip
        # what the design would choose if the arm were its nominal chain
        targets, problems = preview_adaptive_plan(
            plan.kind, cell.spec, env, plan.poses, seed=plan.seed, tool_m=cell.tool_m,
            base_in_tracker=cell.base_in_tracker, config=cfg,
        )  # fmt: skip
        q = np.array([t.q_rad for t in targets])
        ref = reference_poses(cell.spec, env, cell.tool_m)
        ident = identification_lines(cell.spec, env, q, cell.tool_m, cell.base_in_tracker, ref)
        ident += _pose_count(plan, cell, env, cfg, q, ref)
        return {
            **out,
            "problems": problems,
            "ok": not problems,
            "preview": True,
            "identification": ident,
            "reference": _reference(plan, targets),
        }
    ident = []
    if targets:
        q = np.array([t.q_rad for t in targets])
        ref = reference_poses(cell.spec, env, cell.tool_m)
        ident = identification_lines(cell.spec, env, q, cell.tool_m, cell.base_in_tracker, ref)
        if preview:
            ident += _pose_count(plan, cell, env, cfg, None, ref)
    return {
        "adaptive": False,
        "targets": len(targets),
        "problems": problems,
        "ok": not problems and len(targets) > 0,
        "first_q_rad": [np.asarray(t.q_rad).tolist() for t in targets[:3]],
        "identification": ident,
        "reference": _reference(plan, targets),
    }


def _reference(plan: PlanConfig, targets) -> str | None:
    """The dry run's reference line (`campaign --reference-every`), or None."""
    from workcell.campaign.plans import reference_line

    if not (plan.reference_every and targets):
        return None
    return reference_line(targets[0].pose_id, len(targets), plan.reference_every)


def _pose_count(plan: PlanConfig, cell, env, cfg, previewed_q, ref) -> list[str]:
    """The dry run's pose-count line (a second or a few: the Plan screen's check only)."""
    from workcell.campaign.identification import plan_pose_count_line

    line = plan_pose_count_line(
        plan.kind, cell.spec, env, seed=plan.seed, tool_m=cell.tool_m,
        base_in_tracker=cell.base_in_tracker, approach_rad=cfg.approach_rad,
        previewed_q=previewed_q, reference_q=ref,
    )  # fmt: skip
    return [line] if line else []


def envelope_summary(env) -> list[str]:
    lim = np.rad2deg(np.asarray(env.joint_limits_rad))
    rows = [
        "joints (deg): " + " ".join(f"J{j + 1}[{lim[j, 0]:.0f},{lim[j, 1]:.0f}]" for j in range(6)),
        "box (m): "
        + f"{np.round(env.box_min_m, 2).tolist()} .. {np.round(env.box_max_m, 2).tolist()}",
        f"floor {env.floor_z_m:.2f} m, margin {1e3 * env.kinematic_margin_m:g} mm, "
        f"speed <= {env.max_speed_rad_s:g} rad/s",
    ]
    return rows


# ----------------------------------------------------------------------------- live residual
class LiveResidual:
    """Residual of each recorded sample against the nominal model, the base registered (Kabsch)
    on the samples so far (needs 4). Called from the campaign worker thread."""

    MIN_SAMPLES = 4

    def __init__(self, cell) -> None:
        from workcell.kinematics.chain import pack

        self.theta = pack(cell.spec.dh, tool=np.asarray(cell.tool_m, float))
        self.p_base: list[np.ndarray] = []
        self.p_meas: list[np.ndarray] = []

    def update(self, sample: dict) -> dict:
        from workcell.kinematics.chain import p_tracker
        from workcell.kinematics.frames import apply_transform, kabsch

        q = np.asarray(sample["q_measured_rad"], float)[None, :]
        self.p_base.append(np.asarray(p_tracker(self.theta, np.eye(4), q))[0])
        self.p_meas.append(np.asarray(sample["tracker_position_m"], float))
        n = len(self.p_meas)
        if n < self.MIN_SAMPLES:
            return {"n": n, "residual_m": None, "rms_m": None, "residuals_m": []}
        P, M = np.array(self.p_base), np.array(self.p_meas)
        T = kabsch(P, M)
        r = np.linalg.norm(apply_transform(T, P) - M, axis=1)
        return {
            "n": n,
            "residual_m": float(r[-1]),
            "rms_m": float(np.sqrt(np.mean(r**2))),
            "residuals_m": r.tolist(),
        }


class LiveEstimator:
    """The online EKF-ANN estimate (`workcell.estimation.ekf_ann.live.LiveFilter`), fed in its
    own thread so the campaign never waits for it (its initialisation pre-fits a network).

    `submit(sample)` queues a sample; `on_result(index, estimate)` is called from the
    estimator's thread with {"text", "innovation_m", "rms_m" (RMS of the last innovations,
    i.e. the a-priori prediction error), "variance_factor", "initialised"}. If the module is
    missing or fails, `available` is False and `reason` says why; the campaign goes on."""

    WINDOW = 10

    def __init__(self, cell, on_result: Callable[[int, dict], None] | None = None) -> None:
        import queue
        import threading

        self.filter = None
        self.reason = ""
        self.on_result = on_result
        self._innov: list[float] = []
        self._q: queue.Queue = queue.Queue()
        try:
            mod = importlib.import_module("workcell.estimation.ekf_ann.live")
            self.filter = mod.LiveFilter.for_cell(cell)
        except ModuleNotFoundError as e:
            self.reason = f"EKF-ANN unavailable: {e.name} is not in this build"
        except Exception as e:  # noqa: BLE001 - optional estimator: report, go on
            self.reason = f"EKF-ANN unavailable ({type(e).__name__}: {e})"
        self._thread = None
        if self.filter is not None:
            self._thread = threading.Thread(target=self._loop, name="ekf-ann-live", daemon=True)
            self._thread.start()

    @property
    def available(self) -> bool:
        return self.filter is not None

    def submit(self, sample: dict) -> None:
        if self.filter is not None:
            self._q.put(sample)

    def close(self) -> None:
        """Stop after the queued samples (the thread is a daemon; nothing waits for it)."""
        self._q.put(None)

    def _loop(self) -> None:
        while True:
            sample = self._q.get()
            if sample is None or self.filter is None:
                return
            est = self.update(sample)
            if self.on_result is not None:
                self.on_result(int(sample.get("index", -1)), est)

    def update(self, sample: dict) -> dict:
        """Process one sample (blocking); the estimate, or {"error": reason} once it failed."""
        f = self.filter
        if f is None:
            return {"error": self.reason}
        try:
            text = str(f.update(sample))
        except Exception as e:  # noqa: BLE001
            self.filter = None
            self.reason = f"EKF-ANN unavailable (failed: {type(e).__name__}: {e})"
            return {"error": self.reason}
        out: dict = {"text": text, "initialised": getattr(f, "filter", None) is not None}
        innov = getattr(f, "last_innovation_m", float("nan"))
        if out["initialised"] and isinstance(innov, int | float) and np.isfinite(innov):
            self._innov.append(float(innov))
            w = np.array(self._innov[-self.WINDOW :])
            out["innovation_m"] = float(innov)
            out["rms_m"] = float(np.sqrt(np.mean(w**2)))
        vt = getattr(f, "variance_test", None)
        if callable(vt):
            try:
                out["variance_factor"], out["variance_ok"] = vt()
            except Exception:  # noqa: BLE001
                pass
        return out


# ----------------------------------------------------------------------------- campaign
def start_campaign(
    dev: Devices,
    plan: PlanConfig,
    *,
    control,
    on_sample: Callable[[dict], None],
    on_event: Callable[[dict], None],
    resume_from: str | None = None,
):
    """Run a campaign (blocking) -> (path, CampaignResult). With `resume_from`, continue that
    interrupted recording into a new chained file (the plan is re-created from its session)."""
    from workcell.campaign.run import run_campaign

    plan.validate()
    out = Path(plan.out)
    env = None
    cell = dev.cell  # a resume not declaring a payload here: a copy with the recorded one
    if resume_from:
        from workcell.campaign.resume import (
            check_same_cell,
            check_same_plan,
            continuation,
            default_out,
            recorded_config,
            recorded_envelope,
            recorded_reference_every,
            recorded_tool,
            resume_plan,
        )

        old = Path(resume_from)
        info = resume_plan(str(old))
        camp = info["campaign"]
        if int(camp["poses"]) - len(info["done"]) <= 0:
            raise UserError(f"{old}: all {camp['poses']} poses already measured")
        out = default_out(old) if (not plan.out or out == old or out.exists()) else out
        env = recorded_envelope(
            camp,
            dev.cell.spec,
            str(old),
            default=dev.envelope,
            say=lambda m: on_event({"level": "warning", "kind": "envelope", "message": m}),
        )
        check_resume_envelope(plan, env, dev, old)
        recorded = np.asarray(recorded_tool(info["recording"].session))
        if not np.allclose(recorded, dev.cell.tool_m, rtol=0.0, atol=1e-9):
            raise UserError(
                f"{old} was recorded with the SMR offset {recorded.tolist()} m, the Devices screen "
                f"declares {np.asarray(dev.cell.tool_m).tolist()} m: a resume keeps the recorded "
                "one; set it on the Devices screen and reconnect, or start a new campaign"
            )
        rec_pay = info["recording"].session.get("payload") or {}
        pay = rec_pay.get("mass_kg")
        if dev.cell.payload_declared and dev.cell.payload_source != "controller":
            if pay is not None and abs(float(pay) - float(dev.cell.payload_kg)) > 1e-9:
                raise UserError(
                    f"{old} was recorded with a payload of {float(pay):g} kg, the Devices "
                    f"screen declares {float(dev.cell.payload_kg):g} kg: a resume keeps the "
                    "recorded one; set it on the Devices screen and reconnect, or start a new "
                    "campaign"
                )
        elif pay is not None:  # not declared here: the recorded one (the controller's is checked)
            cell = replace(
                dev.cell,
                payload_kg=float(pay),
                payload_com_m=tuple(float(c) for c in (rec_pay.get("com_m") or (0.0, 0.0, 0.0))),
                payload_source="recording",
            )
        check_same_cell(camp, str(old), **_cell_identity(dev))
        check_same_plan(info, dev.cell.spec, env, dev.cell.tool_m, str(old))
        cfg = recorded_config(camp, cell.payload_kg, campaign_config(plan, dev))
        plan = PlanConfig(
            kind=camp["plan"],
            poses=int(camp["poses"]),
            seed=int(camp["seed"]),
            settle_s=cfg.settle_s,
            readings_per_pose=cfg.readings_per_pose,
            envelope=plan.envelope,
            out=str(out),
            warmup_s=cfg.warmup_s,
            reference_every=recorded_reference_every(camp, str(old)),
        )
        kw = continuation(info, old)
    else:
        from workcell.campaign.identification import too_few_to_fit_notes

        cfg = campaign_config(plan, dev)
        kw = {"reference_every": plan.reference_every, "notes": too_few_to_fit_notes(plan.poses)}
    if out.exists():
        raise UserError(f"{out} already exists; choose a new recording path or resume it")
    check_output_path(out, "recording", inputs=[resume_from] if resume_from else [])
    out.parent.mkdir(parents=True, exist_ok=True)
    return run_campaign(
        dev.robot,
        dev.tracker,
        cell,
        out,
        plan=plan.kind,
        poses=plan.poses,
        seed=plan.seed,
        envelope=env if resume_from else envelope_for(plan, dev),
        config=cfg,
        control=control,
        on_sample=on_sample,
        on_event=on_event,
        extra_campaign={**_cell_identity(dev), "ui": "workcell tui"},
        payload_how=TUI_PAYLOAD_HOW,
        **kw,
    )


def check_resume_envelope(plan: PlanConfig, recorded, dev: Devices, old: Path) -> None:
    """A resume keeps the envelope its campaign was recorded with: the command line refuses
    `--resume` with `--envelope`. Here the Plan screen always has one: its default, or a file
    giving the recorded envelope, goes; any other (a tighter one set since) is refused before
    anything moves, as the command line refuses it."""
    if plan.envelope in ("", "default"):
        return
    if envelope_for(plan, dev).to_dict() == recorded.to_dict():
        return
    raise UserError(
        f"envelope {plan.envelope} (Plan screen): a resume keeps the envelope {old.name} was "
        "recorded with (its poses were planned inside it); set the Plan screen's envelope back "
        "to default, or start a new campaign in this envelope"
    )


def _cell_identity(dev: Devices) -> dict:
    """What a recording says of the cell it was made on (`resume.check_same_cell`): the device
    addresses, and for a simulation this program runs its truth (effects, seed)."""
    sim = dev.kind != "hardware"
    return {
        "robot_url": dev.robot_url,
        "tracker_url": dev.tracker_url,
        "effects": dev.config.effects if sim else None,
        "sim_seed": dev.config.seed if sim else None,
    }


# what the campaign screen adds to the command line's resume hint: its own way to resume
RESUME_HERE = " (on this screen: r)"


def stop_report(res, path: str | Path, events=()) -> dict | None:
    """Why the campaign engine ended a campaign by itself (not the operator's abort, not the
    end of the plan), in the command line's words (`run.stop_aftermath`, `run.margin_stop`):
    {"kind": its
    `stopped_by`, "reason": the engine's one line on why, "recording": what the recording
    keeps and how to resume it}. For the margin watch the reason is its `margin` error event
    (`events`: those the campaign sent), and a resume is refused. A campaign that went through
    its plan recording no pose (every pose skipped) is a stop too, kind "nothing recorded", as
    the command line's `campaign_stop` (exit 3) makes it. None otherwise."""
    from workcell.campaign.run import margin_stop, nothing_recorded, resume_hint, stop_aftermath

    if res is None:
        return None
    if res.stopped_by != "margin" and (
        nothing := nothing_recorded(
            res, path, again="with a new recording path (the Plan screen has moved on to one)"
        )
    ):
        return {"kind": "nothing recorded", "reason": nothing[0], "recording": nothing[1]}
    if not res.aborted or res.stopped_by in ("", "operator"):
        return None
    if res.stopped_by == "margin":
        try:
            margin_stop(res, path)
            line = ""
        except UserError as e:
            line = str(e)
        said = [e for e in events if e.get("kind") == "margin" and e.get("level") == "error"]
        return {
            "kind": "margin",
            "reason": str(said[-1]["message"]) if said else line,
            # what a resume of it answers (`run_campaign`'s check of the recording it continues)
            "recording": f"{path} is closed and keeps {res.measured} poses; a resume keeps its "
            "SMR offset and envelope, so start a new campaign instead",
        }
    reason = res.stop_message or res.stopped_by
    kept = stop_aftermath(res, path) or resume_hint(path, res.measured)
    return {"kind": res.stopped_by, "reason": reason, "recording": kept + RESUME_HERE}


def error_stop_report(error: BaseException, path: str | Path | None) -> dict | None:
    """The same for a campaign an error ended after its recording was opened: a device fault
    beyond the retries (`run_campaign` notes the recording on it; the command line's
    `device_errors_say_resume` line), or the arm found outside the envelope with the recording
    kept (its message says to jog it back in). None for any other failure."""
    from workcell.campaign.executor import ArmOutsideEnvelope
    from workcell.campaign.run import resume_hint

    rec = getattr(error, "recording", None)
    if rec is None and isinstance(error, ArmOutsideEnvelope) and path and Path(path).is_file():
        from workcell.recording.reader import read_recording

        try:
            rec = (Path(path), len(read_recording(path).samples))
        except Exception:  # noqa: BLE001 - unreadable: no line about what it keeps
            rec = None
    if rec is None:
        return None
    return {"kind": "error", "reason": str(error), "recording": resume_hint(*rec) + RESUME_HERE}


def check_recording(path: str | Path) -> dict:
    """What a reader sees in a (possibly interrupted) recording."""
    from workcell.recording.reader import read_recording
    from workcell.recording.repeats import repeat_line, repeats_of

    rec = read_recording(path)
    return {
        "path": str(path),
        "samples": len(rec.samples),
        "events": len(rec.events),
        "closed_cleanly": bool(rec.closed_cleanly),
        "problems": list(rec.problems),
        "repeats": [repeat_line(r) for r in repeats_of(rec)],
    }


# ----------------------------------------------------------------------------- fit
def fit(
    recording: str | Path,
    method: str,
    *,
    holdout: float = 0.25,
    model_out: str | Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Fit `method` on the recording with a held-out split; save the model next to it.

    Returns the `fit_dataset` report plus `model` (path) and `residuals` (held-out per-pose
    error before/after, m) for the plot. `ekf-ann` replays the recording through the online
    filter (`workcell.commands.replay`) when that module exists."""
    from workcell.estimation.models import check_model_output, default_model_out

    moved = None
    if model_out:
        out = Path(model_out)
    else:  # beside the recording, unless its folder is read-only (an archive: kept as it is)
        out, moved = default_model_out(recording, f".{method}.model.json")
    check_output_path(out, "model file", inputs=[recording])
    check_model_output(  # over an earlier model of this recording only; no --force here
        out,
        recording,
        remedy="the Fit screen writes its model there: move that file away, or fit on the "
        "command line with --out",
    )
    if method == "ekf-ann":
        report = _replay(recording, progress, holdout, out)
    else:
        report = _fit_and_save(recording, method, holdout, out, progress)
    if moved:
        report["model_note"] = moved
    return report


def _fit_and_save(recording, method: str, holdout: float, out: Path, progress) -> dict:
    """`fit` for the batch methods: fit, save the model at `out`, add the plot's residuals."""
    from workcell.estimation.dh import nominal_registered
    from workcell.estimation.fitting import fit_dataset, keep_in_model
    from workcell.estimation.models import aux_from_dataset, save_model
    from workcell.kinematics.chain import p_tracker
    from workcell.recording.dataset import Dataset

    ds = Dataset.from_recording(recording)
    warnings = _read_warnings(ds, progress)
    model, report = fit_dataset(ds, method=method, holdout=holdout, progress=progress)
    report["recording_problems"], report["read_warnings"] = list(ds.read_problems), warnings
    keep_in_model(model, ds, report)
    report["model"] = str(save_model(model, out))
    _, test = ds.holdout_split(holdout)
    ev = ds.subset(test) if len(test) else ds
    after = np.linalg.norm(model.predict(ev.q, **aux_from_dataset(ev)) - ev.p_tracker, axis=1)
    train, _ = ds.holdout_split(holdout)
    th, base = nominal_registered(ds.subset(train))
    before = np.linalg.norm(np.asarray(p_tracker(th, base, ev.q)) - ev.p_tracker, axis=1)
    report["residuals"] = {"before_m": before.tolist(), "after_m": after.tolist()}
    return report


def _read_warnings(ds, progress) -> list[str]:
    """What the reader could not read of the recording (a damaged chunk, a cut-off end), one
    line each, as `fit` and `diagnose` print them: said through `progress` before the work
    starts, and returned for the report (the app shows them as warnings)."""
    from workcell.recording.dataset import read_warnings

    lines = read_warnings(ds)
    for line in lines if progress else ():
        progress(line)
    return lines


def replay_samples(chain, ds, rows) -> list[dict]:
    """The recorded samples behind data-set rows `rows`, in recording order: what the fits
    kept (`Dataset` screens out gross readings and exact copies, as `workcell replay` does),
    not every sample of those poses."""
    return [chain.samples[int(ds.row[i])] for i in np.sort(np.asarray(rows, int))]


def _replay(recording, progress, holdout: float, out: Path) -> dict:
    """EKF-ANN replay (what `workcell replay --online ekf-ann` does): the training samples in
    recording order through `LiveFilter`, then the final model on the held-out poses."""
    try:
        live = importlib.import_module("workcell.estimation.ekf_ann.live")
    except ModuleNotFoundError:
        raise Unavailable("EKF-ANN replay is not available in this build") from None
    from workcell.estimation.dh import nominal_registered
    from workcell.estimation.models import aux_from_dataset, error_stats, save_model
    from workcell.kinematics.chain import p_tracker
    from workcell.recording.chain import load_chain
    from workcell.recording.dataset import Dataset

    chain = load_chain(recording)  # a resumed recording: every file it continues
    rec = chain.newest
    ds = Dataset.from_recording(chain)
    warnings = _read_warnings(ds, progress)
    train, test = ds.holdout_split(holdout)
    samples = replay_samples(chain, ds, train)
    try:
        lf = live.LiveFilter.from_session(rec.session)
    except (KeyError, ValueError) as e:
        raise UserError(f"{recording}: session unusable for the online filter ({e})") from None
    if len(samples) < getattr(lf, "n_init", 0):
        raise UserError(
            f"EKF-ANN replay: {len(samples)} training samples, the filter needs {lf.n_init} "
            "to initialise"
        )
    t0 = time.perf_counter()
    line = ""
    for k, smp in enumerate(samples):
        line = lf.update(smp)
        if progress and (k % 10 == 0 or k == len(samples) - 1):
            progress(line)
    model = lf.model()
    ev = ds.subset(test) if len(test) else ds.subset(train)
    dtr = ds.subset(train)
    th, base = nominal_registered(dtr)
    pred = model.predict(ev.q, **aux_from_dataset(ev))
    held = error_stats(pred, ev.p_tracker, interval=True)
    nom_pred = np.asarray(p_tracker(th, base, ev.q))
    nominal = error_stats(nom_pred, ev.p_tracker, interval=True)
    for k, v in ds.provenance().items():  # for the next fit to know it as its own
        model.info.setdefault(k, v)
    report = {
        "method": "ekf-ann",
        "recording": ds.source,
        "train_poses": int(len(train)),
        "heldout_poses": int(len(test)),
        "nominal_rms_m": nominal["rms_m"],
        "nominal_rms_ci95_m": nominal["rms_ci95_m"],
        "nominal_max_m": nominal["max_m"],
        "heldout_rms_m": held["rms_m"],
        "heldout_rms_ci95_m": held["rms_ci95_m"],
        "heldout_max_m": held["max_m"],
        "fit_seconds": time.perf_counter() - t0,
        "estimate": lf.estimate(),
        "last_line": line,
        "recording_problems": list(ds.read_problems),
        "read_warnings": warnings,
        "model": str(save_model(model, out)),
        "residuals": {
            "before_m": np.linalg.norm(nom_pred - ev.p_tracker, axis=1).tolist(),
            "after_m": np.linalg.norm(pred - ev.p_tracker, axis=1).tolist(),
        },
    }
    return report


# ----------------------------------------------------------------------------- diagnose
def diagnose(
    recording: str | Path, *, quick: bool = False, progress: Callable[[str], None] | None = None
) -> dict:
    """The discovery report (`workcell.estimation.discovery.diagnose`) as a plain dict with the
    held-out residuals before/after for the plot. As `workcell diagnose`, the non-parametric
    residual check runs (its "What is not explained" sentence ends the summary); `quick` skips
    it (`--no-np`), and then `np_check_note` says so, with what is left unexplained untested."""
    try:
        disc = importlib.import_module("workcell.estimation.discovery")
    except ModuleNotFoundError:
        raise Unavailable("diagnosis (discovery) is not available in this build") from None
    fn = getattr(disc, "diagnose", None)
    if fn is None:
        raise Unavailable("diagnosis: workcell.estimation.discovery has no diagnose()")
    from workcell.recording.dataset import Dataset

    ds = Dataset.from_recording(recording)
    warnings = _read_warnings(ds, progress)
    cfg = disc.DiagnoseConfig(nonparametric=not quick) if hasattr(disc, "DiagnoseConfig") else None
    diag = fn(ds, cfg, progress=progress)
    rep = dict(diag.report)
    rep["recording_problems"], rep["read_warnings"] = list(ds.read_problems), warnings
    if "np_test" not in (rep.get("unexplained") or {}):
        rep["np_check_note"] = np_check_note(rep, quick)
    plots = getattr(diag, "plots", {}) or {}
    if "res_before" in plots and "res_after" in plots:
        rep["residuals"] = {
            "before_m": np.linalg.norm(np.asarray(plots["res_before"]), axis=1).tolist(),
            "after_m": np.linalg.norm(np.asarray(plots["res_after"]), axis=1).tolist(),
        }
    return rep


def np_check_note(rep: dict, quick: bool) -> str:
    """The line a diagnosis without the non-parametric residual check ends with in place of the
    command line's "What is not explained" sentence: the size above the noise floor (computed
    without the check), and that it was not tested for structure, and how to test it."""
    from workcell.estimation.models import unexplained_text

    u = rep.get("unexplained") or {}
    size = ""
    if u.get("excess_over_floor_m") is not None:
        size = (
            unexplained_text(
                {"rms_m": u["excess_over_floor_m"], "upper_m": u.get("excess_over_floor_upper_m")}
            )
            + "; "
        )
    why = "quick was ticked" if quick else "it did not run"
    return (
        f"What is not explained: {size}not tested for structure: the non-parametric residual "
        f"check was skipped ({why}). Untick quick and diagnose again, or run `workcell diagnose "
        f"{rep.get('recording', 'REC')}` (the command line runs it unless --no-np)."
    )


# ----------------------------------------------------------------------------- export
EXPORT_FORMATS = ("table", "urscript", "ros-yaml")


@dataclass
class ExportConfig:
    model: str = ""
    format: str = "table"
    out: str = "correction"
    volume: str = ""  # x0,y0,z0,x1,y1,z1 (m, base) or empty for the default box
    spacing_m: float | None = None  # fixed spacing (skips refinement) or None
    max_correction_m: float = 5e-3


def export(cfg: ExportConfig, log: Callable[[str], None] | None = None) -> dict:
    """Write the correction (`workcell.export`); returns the summary with its validation
    numbers. Refusals (`CorrectionRefused`) propagate as UserError with one clear line."""
    try:
        build = importlib.import_module("workcell.export.build")
    except ModuleNotFoundError:
        raise Unavailable("export is not available in this build") from None
    from workcell.estimation.models import load_model

    if cfg.format not in EXPORT_FORMATS:
        raise UserError(f"format {cfg.format!r}: choose {', '.join(EXPORT_FORMATS)}")
    if not cfg.model:
        raise UserError("choose a fitted model first (fit a recording on the Fit screen)")
    if not Path(cfg.model).exists():
        raise UserError(f"model file {cfg.model} does not exist")
    from workcell.errors import refuse_overwrite
    from workcell.export.files import check_export_outputs, output_files, output_kinds
    from workcell.export.frame import frame_lines

    out = check_output_path(cfg.out, "output")
    outputs = output_files(cfg.format, out)
    # never over the model or a recording; over another file only if it is an earlier export
    refuse_overwrite(outputs, [cfg.model], "output")
    check_export_outputs(
        outputs, False, log or (lambda m: None), kinds=output_kinds(cfg.format), named=out
    )
    model = load_model(cfg.model)
    # the folder the files go to, and whether it is new (the screen and notice say both)
    summary: dict = {"format": cfg.format, "model": cfg.model, "folder": str(out.parent)}
    summary["new_folder"] = not out.parent.is_dir()
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if cfg.format == "ros-yaml":
        from workcell.export.ros_yaml import export_ros_yaml

        rec, sha = build.model_recording(model)
        path, info = export_ros_yaml(model, out, meta={"model": cfg.model, "recording_sha256": sha})
        info = info or {}
        summary["files"] = [str(path)]
        summary["validation"] = {k: v for k, v in info.items() if isinstance(v, int | float | str)}
        # what `workcell export` prints for it (the frame its targets are in), and what the
        # model leaves out, in neither the YAML's values nor their +- (its JSON summary)
        summary["base_correction_line"] = info.get("base_correction_line")
        summary["unexplained"] = info.get("model_unexplained")
        summary["unexplained_without_outliers"] = info.get("model_unexplained_without_outliers")
        summary["seconds"] = time.perf_counter() - t0
        return summary
    volume = build.parse_vec(cfg.volume, 6, "volume") if cfg.volume.strip() else None
    table, _ = build.make_table(
        model,
        model_path=cfg.model,
        volume=volume,
        max_correction_m=cfg.max_correction_m,
        spacing_m=cfg.spacing_m,
        log=log,
    )
    summary["grid"] = {"shape": list(table.shape), "spacing_m": table.spacing_m.tolist()}
    # the base-correction line `workcell export` prints for a table: targets in another estimate
    # of the robot base differ from base_ref by the fitted base correction
    summary["base_correction_line"] = frame_lines(table.meta, "the table's nodes")[2]
    summary["validation"] = {
        k: table.meta.get(k)
        for k in (
            "max_interp_error_m",
            "rms_interp_error_m",
            "target_interp_error_m",
            "interp_error_target_met",
            "interp_error_points",
            "max_correction_m",
            "correction_bound_m",
            "median_std_m",
            "max_std_m",
            "nodes_std_exceeds_correction",
        )
    }
    summary["joint_coverage"] = table.meta.get("joint_coverage")
    summary["conditions"] = list(table.meta.get("conditions_note") or [])
    # what the model leaves out, not in the table's 1-sigma (as `workcell export` prints it)
    summary["unexplained"] = table.meta.get("model_unexplained")
    summary["unexplained_without_outliers"] = table.meta.get("model_unexplained_without_outliers")
    if cfg.format == "table":
        summary["files"] = [str(p) for p in table.save(out)]
    else:
        from workcell.export.urscript import size_warning, write_urscript

        script = out if out.suffix else out.with_suffix(".script")
        summary["files"] = [str(write_urscript(table, script))] + [
            str(p)
            for p in table.save(script)  # X.script -> X.json, X.csv
        ]
        summary["script_size_warning"] = size_warning(script)
    summary["seconds"] = time.perf_counter() - t0
    return summary


# ----------------------------------------------------------------------------- closed loop
def closed_loop(
    model_path: str,
    table_path: str,
    dev: Devices,
    targets: int | None = None,
    *,
    readings: int | None = None,
    log: Callable[[str], None] | None = None,
    envelope_file: str = "default",
    abort: threading.Event | None = None,
) -> dict:
    """`workcell validate` on the connected cell: random targets in the table's volume, each
    measured by the tracker uncorrected and corrected through the table; every motion checked
    against the cell's envelope first: the Plan screen's envelope file when one is set, else the
    one recorded with the model's campaign, else the arm's default (`validation_envelope`).
    Measured by the tracker, as on a real cell (in simulation too: the simulated tracker's noise
    is in the numbers). `abort` (set by the operator) stops a move under way (a driver with
    `abort_requested`) and any later one: the arm is stopped and `UserError` says so."""
    from workcell.campaign.envelope import Guard
    from workcell.drivers.protocols import driver_hooks
    from workcell.estimation.models import load_model
    from workcell.export.build import model_recording, model_session, nominal_for_model
    from workcell.export.table import load_table
    from workcell.export.validate import (
        DEFAULT_READINGS,
        DEFAULT_TARGETS,
        MAX_TARGETS,
        robot_mover,
        run_validation,
        thermal_mismatch,
        tracker_measure,
        validation_envelope,
        validation_warnings,
    )

    targets = DEFAULT_TARGETS if targets is None else targets
    if not 1 <= targets <= MAX_TARGETS:
        raise UserError(f"targets must be 1..{MAX_TARGETS}, got {targets}")
    readings = DEFAULT_READINGS if readings is None else readings
    if not table_path or not Path(table_path).exists():
        raise UserError("export a table first (the check moves the arm to its corrected targets)")
    model = load_model(model_path)
    table = load_table(table_path)
    nominal = nominal_for_model(model)
    from workcell.export.validate import table_model_mismatch

    why = table_model_mismatch(table, nominal, model_recording(model)[1], model=model, ui=True)
    if why is not None:
        raise UserError(f"{table_path}: {why}")
    spec = dev.cell.spec
    rec, _ = model_recording(model)
    session, _ = model_session(model)
    given = None
    if envelope_file not in ("", "default"):
        from workcell.campaign.envelope import load_envelope

        given = load_envelope(envelope_file, spec)
    env, env_what = validation_envelope(given, session, spec, str(rec), default=dev.envelope)
    if log:
        log(f"moves checked against {env_what}")
    from workcell.export.validate import payload_check

    warnings: list[str] = []
    try:  # the in-process simulation's payload is known; a controller's as read at connect
        w = payload_check(model, table, dev.cell.payload_kg, ui=True,
                          simulated=dev.kind == "in-process simulation",
                          source=dev.cell.payload_source)  # fmt: skip
    except UserError as e:
        raise UserError(f"{table_path}: {e}") from None
    if w is not None:
        warnings.append(w)
        if log:
            log(f"warning: {w}")
    if not np.allclose(nominal.tool_m, dev.cell.tool_m, rtol=0.0, atol=1e-6):
        raise UserError(
            f"the model was fitted with the SMR at {np.round(nominal.tool_m, 6).tolist()} m on "
            f"the flange, the Devices screen declares {np.round(dev.cell.tool_m, 6).tolist()} m: "
            "the table corrects the model's SMR; mount and declare that one, then reconnect"
        )
    dev.robot.connect()  # as a campaign does; it closes them when it ends (`Held`: the app's
    dev.tracker.connect()  # stay open for its status poll)
    abort = abort or threading.Event()
    mover = robot_mover(dev.robot, *env.cap(0.5, 1.0))

    def move(q: np.ndarray) -> None:
        if abort.is_set():
            raise KeyboardInterrupt
        mover(q)
        if abort.is_set():  # stopped on the way, or arrived as the abort came
            raise KeyboardInterrupt

    try:
        # the arm's joint temperatures now (None if the controller does not report them)
        if w := thermal_mismatch(model, table, dev.robot.state().temperature_c, ui=True):
            warnings.append(w)
            if log:
                log(f"warning: {w}")
        with driver_hooks(dev.robot, abort_requested=abort.is_set):
            res = run_validation(
                nominal,
                table,
                move,
                tracker_measure(dev.tracker, readings),
                n=targets,
                seed=12345,
                guard=Guard(env, spec, nominal.tool_m),  # the SMR the campaign declared
                q_start=lambda: np.asarray(dev.robot.state().q_rad, float),
                log=log,
                clock=lambda: float(dev.robot.state().t_s),  # the controller's time
            )
    except BaseException:
        if not abort.is_set():
            raise
        try:  # stopped already if a move was under way (robot_mover); said to the arm anyway
            dev.robot.stop()
        except Exception:  # noqa: BLE001 - a lost connection stops the controller's program
            pass
        raise UserError(
            "closed-loop check aborted: the arm is stopped where it was; no result (run it "
            "again for one)"
        ) from None
    finally:
        close_quietly(dev.robot, dev.tracker)
    res["warnings"] = warnings + validation_warnings(res)
    res["envelope"] = env_what
    res["truth"] = "tracker"
    res["table"] = str(table_path)
    return res
