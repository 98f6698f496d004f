"""The UI's long jobs, run in worker threads: each reports by posting messages (`messages`) to
the app, which updates the screens. `backend` does the device and file work without Textual;
a job wires it to the messages."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from textual.message import Message

from workcell.errors import UserError
from workcell.tui import backend
from workcell.tui import messages as m
from workcell.tui.backend import Devices, PlanConfig


def campaign_job(
    post: Callable[[Message], object],
    dev: Devices,
    plan: PlanConfig,
    control,
    *,
    resume_from: str | None,
    online: bool,
) -> None:
    """One campaign (or the resume of `resume_from`) on the connected cell, start to end.

    The dry run checks the plan first (nothing moves when it finds a problem; a resume keeps the
    recorded plan); the live residual and, when `online`, the online EKF-ANN estimate follow
    every sample; the reference pose measured again is reported as an event. Ends with a
    `CampaignFinished` message in every case: with the recording's check, or, after an error,
    with the stop report and what the recording kept. An error that is not a campaign stop
    (a programming error) is raised again after that message."""
    path = None
    out = plan.out  # the recording (a resume's new file, once worked out)
    try:
        if not resume_from:
            chk = backend.dry_run(plan, dev, preview=False)
            post(m.PlanChecked(plan, chk))
            if not chk["ok"]:
                raise UserError(f"dry run found {len(chk['problems'])} problem(s); nothing moved")
        live = backend.LiveResidual(dev.cell)
        est = None
        note = "EKF-ANN off"
        if online and not control.abort.is_set():  # aborted: no time for it
            est = backend.LiveEstimator(
                dev.cell, on_result=lambda i, e: post(m.EstimateUpdated(i, e))
            )
            note = "" if est.available else "EKF-ANN unavailable"
        from workcell.recording.repeats import RepeatWatch, repeat_event_line

        if resume_from:
            from workcell.campaign.plans import reference_repeats
            from workcell.campaign.resume import (
                default_out,
                recorded_reference_every,
                resume_plan,
            )

            info = resume_plan(resume_from)
            left = int(info["campaign"]["poses"]) - len(info["done"])
            every = recorded_reference_every(info["campaign"], resume_from)
            refs = reference_repeats(left, every)
            total = left + refs
            old = Path(resume_from)
            if not out or Path(out) == old or Path(out).exists():
                out = str(default_out(old))
            plan_run = PlanConfig(**{**plan.__dict__, "out": out})
            repeats = RepeatWatch(info["history"])
        else:
            total = plan.measurements()
            refs = total - plan.poses
            plan_run = plan
            repeats = RepeatWatch()
        post(m.CampaignStarted(total, out, note, refs))
        if est is not None and not est.available:
            post(m.CampaignEvent({"level": "info", "kind": "ekf-ann", "message": est.reason}))

        def on_sample(s: dict) -> None:
            post(m.SampleRecorded(s, live.update(s), None))
            if (r := repeats.update(s)) is not None:  # the reference measured again
                line = repeat_event_line(r)
                post(m.CampaignEvent({"level": "info", "kind": "reference", "message": line}))
            if est is not None:
                est.submit(s)

        def on_event(e: dict) -> None:
            post(m.CampaignEvent(e))

        try:
            path, result = backend.start_campaign(
                dev,
                plan_run,
                control=control,
                on_sample=on_sample,
                on_event=on_event,
                resume_from=resume_from,
            )
        finally:
            if est is not None:
                est.close()
        post(m.CampaignFinished(str(path), result, backend.check_recording(path)))
    except BaseException as e:
        rec = None
        # an error after the recording was opened (a device fault beyond the retries): the
        # engine stopped the campaign, the recording keeps what it measured
        stop = backend.error_stop_report(e, out)
        p = Path(out) if out else None
        if path is None and p is not None and p.exists():
            try:
                rec = backend.check_recording(p)
            except Exception:  # noqa: BLE001
                rec = None
        post(m.CampaignFinished(None, None, rec, stop))
        if stop is None:
            raise
