"""Messages of the terminal UI. Screens post requests up to the app (which owns the devices and
the workers); workers post results up from their threads (`post_message` is thread-safe); the app
then sets attributes on the screens (attributes flow down)."""

from __future__ import annotations

from textual.message import Message


# ----------------------------------------------------------------------------- requests (screen -> app)
class ConnectRequested(Message):
    def __init__(self, config) -> None:  # backend.DeviceConfig
        super().__init__()
        self.config = config


class DisconnectRequested(Message):
    pass


class StatusRequested(Message):
    pass


class DryRunRequested(Message):
    def __init__(self, plan) -> None:  # backend.PlanConfig
        super().__init__()
        self.plan = plan


class CampaignStartRequested(Message):
    """Sent after the operator confirmed; `resume_from` continues an interrupted recording."""

    def __init__(self, plan, resume_from: str | None = None) -> None:
        super().__init__()
        self.plan = plan
        self.resume_from = resume_from


class PauseRequested(Message):
    """Toggle pause/resume of the running campaign (takes effect between poses)."""


class AbortRequested(Message):
    """Abort the running campaign (already confirmed by the operator)."""


class FitRequested(Message):
    def __init__(self, recording: str, method: str, holdout: float) -> None:
        super().__init__()
        self.recording, self.method, self.holdout = recording, method, holdout


class DiagnoseRequested(Message):
    def __init__(self, recording: str, quick: bool) -> None:
        super().__init__()
        self.recording, self.quick = recording, quick


class ExportRequested(Message):
    def __init__(self, config) -> None:  # backend.ExportConfig
        super().__init__()
        self.config = config


class ValidateRequested(Message):
    """Closed-loop check of the exported table on the connected cell (`targets` random targets)."""

    def __init__(self, model: str, table: str, targets: int) -> None:
        super().__init__()
        self.model, self.table, self.targets = model, table, targets


class ValidateAbortRequested(Message):
    """Stop the running closed-loop check: the arm stops where it is, no result."""


# ----------------------------------------------------------------------------- results (worker -> app)
class DevicesOpened(Message):
    def __init__(self, devices, status: dict) -> None:
        super().__init__()
        self.devices, self.status = devices, status


class DeviceStatus(Message):
    def __init__(self, status: dict) -> None:
        super().__init__()
        self.status = status


class PlanChecked(Message):
    def __init__(self, plan, result: dict) -> None:
        super().__init__()
        self.plan, self.result = plan, result


class CampaignStarted(Message):
    """`total` measurements to make: poses, plus the reference's repeats (`references`)."""

    def __init__(self, total: int, recording: str, ekf_note: str, references: int = 0) -> None:
        super().__init__()
        self.total, self.recording, self.ekf_note = total, recording, ekf_note
        self.references = references


class SampleRecorded(Message):
    """One recorded pose with the live residual (and EKF-ANN estimate if available)."""

    def __init__(self, sample: dict, live: dict, estimate: dict | None) -> None:
        super().__init__()
        self.sample, self.live, self.estimate = sample, live, estimate


class EstimateUpdated(Message):
    """The online EKF-ANN estimate after sample `index` (from the estimator's own thread)."""

    def __init__(self, index: int, estimate: dict) -> None:
        super().__init__()
        self.index, self.estimate = index, estimate


class CampaignEvent(Message):
    def __init__(self, event: dict) -> None:
        super().__init__()
        self.event = event


class CampaignFinished(Message):
    """`stop_report`: why the campaign engine ended it by itself (`backend.stop_report`); for a
    result the app works it out itself, for an error the worker gives it. (Not `stop`: that is
    Textual's `Message.stop()`, which bubbling calls.)"""

    def __init__(
        self, path: str | None, result, recording: dict | None, stop_report: dict | None = None
    ) -> None:
        super().__init__()
        self.path, self.result, self.recording = path, result, recording
        self.stop_report = stop_report


class JobProgress(Message):
    def __init__(self, job: str, text: str) -> None:
        super().__init__()
        self.job, self.text = job, text


class FitFinished(Message):
    def __init__(self, report: dict) -> None:
        super().__init__()
        self.report = report


class DiagnoseFinished(Message):
    def __init__(self, report: dict) -> None:
        super().__init__()
        self.report = report


class ExportFinished(Message):
    def __init__(self, summary: dict) -> None:
        super().__init__()
        self.summary = summary


class ValidateFinished(Message):
    def __init__(self, result: dict) -> None:
        super().__init__()
        self.result = result


class JobFailed(Message):
    """A worker failed; the app notifies (never crashes). `job`: connect, dry-run, campaign, ..."""

    def __init__(self, job: str, error: str) -> None:
        super().__init__()
        self.job, self.error = job, error
