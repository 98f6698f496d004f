"""A campaign against a controller of another arm than `--model` is refused before any motion
(the audit's UR10 run as a UR5e put 5 postures 39 mm above the envelope's box)."""

import subprocess
import sys

import pytest

from sim_devices.ur_process import SimProcess


@pytest.mark.slow  # moved out of `make test` on 2026-11-26 (its time; tests/test_ur_sim.py
# refuses another arm at the driver); `make test-all` runs it
def test_campaign_refuses_a_ur10_controller_with_model_ur5e(tmp_path):
    out = tmp_path / "c.mcap"
    with SimProcess("127.0.0.46", seed=2, time_scale=20.0, with_tracker=True, robot="ur10") as sim:
        base = [sys.executable, "-m", "workcell.cli", "campaign"]
        dev = ["--robot", f"ur://{sim.info['ur_host']}", "--tracker"]
        dev += [f"serial://{sim.info['tracker_port']}", "--time-scale", "20", "--poses", "4"]
        r = subprocess.run(
            [*base, *dev, "--out", str(out)], capture_output=True, text=True, timeout=300
        )
        err = [x for x in r.stderr.splitlines() if x.strip()]
        assert r.returncode != 0
        assert len(err) == 1 and "the controller says it is a UR10 but --model is ur5e" in err[0]
        assert not out.exists()
        ok = subprocess.run(
            [*base, *dev, "--model", "ur10", "--out", str(out)],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert ok.returncode == 0, ok.stderr[-2000:]
