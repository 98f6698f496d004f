"""The Devices screen's payload (and `workcell tui --payload`): what a campaign from the TUI
records, as `workcell campaign --payload` does on the command line."""

from __future__ import annotations

import pytest

from workcell.campaign.executor import CampaignControl
from workcell.errors import UserError
from workcell.recording.reader import read_recording
from workcell.tui import backend
from workcell.tui.backend import DeviceConfig, PlanConfig
from workcell.tui.screens.devices import config_changes


def _campaign(dev, out, poses=4, stop_after=None):
    control = CampaignControl()

    def on_sample(s):
        if stop_after is not None and s["index"] + 1 >= stop_after:
            control.abort.set()

    plan = PlanConfig(poses=poses, readings_per_pose=1, settle_s=0.1, out=str(out))
    return backend.start_campaign(
        dev, plan, control=control, on_sample=on_sample, on_event=lambda e: None, resume_from=None
    )


def test_the_declared_payload_is_recorded_and_a_resume_keeps_the_recorded_one(tmp_path):
    dev = backend.open_devices(DeviceConfig(effects="none", payload="1.5,0,0,0.02"))
    try:
        # the simulated controller is set to its cell's own payload, not 1.5 kg: said at connect
        assert dev.cell.payload_kg == 1.5 and len(dev.notes) == 1, dev.notes
        assert "controller is set to" in dev.notes[0] and "1.5 kg" in dev.notes[0]
        path, res = _campaign(dev, tmp_path / "p.mcap", poses=5, stop_after=2)
    finally:
        dev.close()
    rec = read_recording(path)
    pay = rec.session["payload"]
    assert (pay["mass_kg"], pay["com_m"], pay["source"]) == (1.5, [0.0, 0.0, 0.02], "declared")
    assert {s["payload_kg"] for s in rec.samples} == {1.5}
    said = [e for e in rec.events if e["kind"] == "payload"]  # and recorded by the campaign
    assert [e["level"] for e in said] == ["warning"] and "1.5 kg" in said[0]["message"]
    # resumed with another payload on the Devices screen: refused before anything moves
    dev = backend.open_devices(DeviceConfig(effects="none", payload="2"))
    try:
        plan = PlanConfig(poses=5, readings_per_pose=1, settle_s=0.1, out=str(tmp_path / "q.mcap"))
        with pytest.raises(UserError, match="recorded with a payload of 1.5 kg") as ei:
            backend.start_campaign(dev, plan, control=CampaignControl(), on_sample=lambda s: None,
                                   on_event=lambda e: None, resume_from=str(path))  # fmt: skip
        assert "\n" not in str(ei.value)
    finally:
        dev.close()
    assert not list(tmp_path.glob("*.resumed*.mcap"))


def test_the_form_says_a_payload_typed_without_reconnecting():
    assert config_changes(DeviceConfig(), DeviceConfig(payload="2")) == [
        "payload 2 (connected: not declared)"
    ]
    assert config_changes(DeviceConfig(payload="2"), DeviceConfig(payload="2")) == []


def test_without_a_declared_payload_the_controllers_setting_is_used(tmp_path):
    """The protocol simulators (a controller reached over RTDE): nothing typed in Payload, so
    the controller's payload setting is read at connect, shown, and recorded."""
    cfg = DeviceConfig(effects="none", start_sim=True, sim_host="127.0.0.88", time_scale=10.0)
    dev = backend.open_devices(cfg)
    try:
        assert dev.kind == "protocol simulators"
        assert dev.cell.payload_source == "controller" and dev.cell.payload_kg > 0
        assert len(dev.notes) == 1 and "payload from the controller's setting" in dev.notes[0]
        assert "--payload" not in dev.notes[0]  # the form's word for it
        path, res = _campaign(dev, tmp_path / "c.mcap", poses=2)
    finally:
        dev.close()
    pay = read_recording(path).session["payload"]
    assert pay["source"] == "controller" and pay["mass_kg"] == dev.cell.payload_kg
