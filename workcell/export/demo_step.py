"""The last step of `workcell demo`: export the best model's correction and prove it in closed loop
on the simulated robot (truth = the simulated physics)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from workcell.export.correction import Conditions
from workcell.export.validate import run_validation, sim_measure

if TYPE_CHECKING:
    import os

    from workcell.campaign.run import CellSetup
    from workcell.estimation.models import FittedModel

N_TARGETS = 50


def correction_step(
    world: Any,  # the simulated world (sim_devices), which export does not import
    cell: CellSetup,
    model: FittedModel,
    method: str,
    out_dir: str | os.PathLike,
    log: Callable[[str], None],
) -> dict:
    from workcell.campaign.envelope import Guard, default_envelope
    from workcell.export.build import make_table
    from workcell.export.urscript import write_urscript

    out = Path(out_dir)
    log(f"correction: table from the {method} model")
    cond = Conditions(
        approach_sign=np.ones(6),
        joint_temperature_c=np.asarray(world.joint_temperatures_c(), float),
        payload_kg=float(cell.payload_kg),
    )
    table, corr = make_table(model, model_path=f"{method} (demo)", conditions=cond, log=log)
    files = {}
    pj, pc = table.save(out / f"correction-{method}")
    files["table_json"], files["table_csv"] = str(pj), str(pc)
    files["urscript"] = str(write_urscript(table, out / f"correction-{method}.script"))
    try:
        from workcell.export.ros_yaml import export_ros_yaml

        files["ros_yaml"] = str(export_ros_yaml(model, out / f"calibration-{method}.yaml")[0])
    except Exception as e:  # noqa: BLE001 - the YAML is optional in the demo (non-DH models)
        log(f"  ros-yaml: skipped ({e})")
    env = default_envelope(cell.spec)

    def move(q):
        world.clock.advance(world.command_move(np.asarray(q, float), 0.5, 1.0))
        world.clock.advance(0.5)

    res = run_validation(
        corr.nominal,
        table,
        move,
        sim_measure(world),
        n=N_TARGETS,
        seed=12345,
        guard=Guard(env, cell.spec, cell.tool_m),
        q_start=lambda: np.asarray(world.joint_state()[0], float),  # read before every move
        log=log,
        clock=world.clock.now,
    )
    held = (getattr(model, "info", {}) or {}).get("heldout_rms_m")
    return {
        "method": method,
        "before_rms_m": res["before_rms_m"],
        "after_rms_m": res["after_rms_m"],
        "targets": res["targets"],
        "improvement": res["improvement"],
        "before": res["before"],
        "after": res["after"],
        "model_heldout_rms_m": held,
        "table": {
            "shape": list(table.shape),
            "spacing_m": table.spacing_m.tolist(),
            "max_interp_error_m": table.meta["max_interp_error_m"],
            "max_correction_m": table.meta["max_correction_m"],
        },
        "files": files,
    }
