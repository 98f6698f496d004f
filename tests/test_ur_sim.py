"""The simulated UR controller through the real, unmodified ur_rtde client, and the UrRobot driver.

Every simulator runs in its own process (`SimProcess`, time-scaled) on its own loopback address
127.0.0.2x, so this module does not clash with other tests; each process is stopped at teardown.
"""

from __future__ import annotations

import os
import socket
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rtde_receive")

import dashboard_client  # noqa: E402
import rtde_control  # noqa: E402
import rtde_receive  # noqa: E402

from sim_devices.ur_process import SimProcess  # noqa: E402
from workcell.drivers.protocols import (  # noqa: E402
    DeviceError,
    DeviceUnreachable,
    ProtectiveStop,
    Robot,
)
from workcell.drivers.ur_robot import MoveAborted, UrRobot, WrongRobotModel  # noqa: E402

TS = 10.0  # simulated seconds per wall second
HOME = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
QA = np.array([0.3, -1.2, 1.3, -1.7, -1.4, 0.4])
QB = np.array([-0.2, -1.8, 1.9, -1.4, -1.7, -0.3])


@pytest.fixture(scope="module")
def sim():
    sp = SimProcess("127.0.0.21", seed=3, time_scale=TS)
    sp.start()
    try:
        yield sp
    finally:
        sp.stop()


@pytest.fixture
def robot_factory():
    made: list[UrRobot] = []

    def make(host: str) -> UrRobot:
        r = UrRobot(host, time_scale=TS, model="ur5e")  # the simulators' default arm
        made.append(r)
        return r

    yield make
    for r in made:
        r.close()


def test_process_announces_itself(sim):
    assert sim.info["ur_host"] == "127.0.0.21"
    assert sim.info["pid"] == sim.pid and sim.pid > 0
    assert sim.info["time_scale"] == TS
    st = sim.state()
    assert st["ok"] and len(st["q_rad"]) == 6


def test_receive_interface_default_recipe_reads_joints(sim):
    rr = rtde_receive.RTDEReceiveInterface("127.0.0.21")  # the ~40-output default recipe
    try:
        q_true = np.array(sim.state()["q_rad"])
        q = np.array(rr.getActualQ())
        assert q.shape == (6,)
        assert np.max(np.abs(q - q_true)) < 1e-4
        assert rr.getRobotMode() == 7 and rr.getSafetyMode() == 1
        temps = np.array(rr.getJointTemperatures())
        assert np.all((temps > 15.0) & (temps < 60.0))
        t0 = rr.getTimestamp()
        time.sleep(0.2)
        dt = rr.getTimestamp() - t0
        assert 0.5 * 0.2 * TS < dt < 2.0 * 0.2 * TS  # the clock runs TS times faster
        # the shoulder holds the arm against gravity: clearly non-zero current
        assert abs(rr.getActualCurrent()[1]) > 0.1
        assert len(rr.getActualTCPPose()) == 6
    finally:
        rr.disconnect()


def test_control_interface_movej_arrives_and_dashboard_answers(sim):
    rr = rtde_receive.RTDEReceiveInterface(
        "127.0.0.21", -1.0, ["timestamp", "actual_q", "runtime_state"]
    )
    rc = rtde_control.RTDEControlInterface("127.0.0.21")
    db = dashboard_client.DashboardClient("127.0.0.21")
    try:
        assert rc.isProgramRunning()
        assert rc.moveJ(QA.tolist(), 1.0, 2.0) is True  # blocking: returns on arrival
        assert np.max(np.abs(np.array(sim.state()["q_rad"]) - QA)) < 1e-9
        # our receive stream may be one packet (8 ms of wall time) behind the control stream
        t_end = time.monotonic() + 0.5
        while np.max(np.abs(np.array(rr.getActualQ()) - QA)) > 1e-4:
            assert time.monotonic() < t_end, "receive stream never showed the arrival"
            time.sleep(0.005)
        db.connect()
        assert db.robotmode() == "Robotmode: RUNNING"
        assert db.safetystatus() == "Safetystatus: NORMAL"
        assert db.isInRemoteControl()
        assert db.polyscopeVersion().startswith("5.15.0")
        assert db.getRobotModel() == "UR5"  # a UR5e answers its family name
        assert db.running()
        assert db.programState().startswith("PLAYING")
        rc.stopScript()
        time.sleep(0.05)
        assert not db.running()
        assert rr.getRuntimeState() == 1
    finally:
        rc.disconnect()
        rr.disconnect()
        db.disconnect()


def test_urrobot_moves_and_reports_state(sim, robot_factory):
    r = robot_factory("127.0.0.21")
    assert isinstance(r, Robot)
    r.connect()
    s0 = r.state()
    r.move_joints(QB, 1.0, 2.0)
    s1 = r.state()
    assert np.max(np.abs(s1.q_rad - QB)) < 1e-4
    assert np.max(np.abs(s1.qd_rad_s)) < 1e-3
    assert s1.t_s > s0.t_s
    assert s1.mode == "RUNNING" and s1.safety == "NORMAL"
    assert s1.temperature_c.shape == (6,) and s1.current_a.shape == (6,)
    assert abs(s1.torque_nm[1]) > 1.0  # shoulder torque against gravity
    # torques follow the pose (gravity), so two poses give different shoulder torques
    r.move_joints(QA, 1.0, 2.0)
    assert abs(r.state().torque_nm[1] - s1.torque_nm[1]) > 0.1
    t_w = time.monotonic()
    t_r = r.state().t_s
    r.sleep(1.0)
    assert time.monotonic() - t_w < 0.8  # 1 s of robot time at TS = 10 is 0.1 s (unscaled: 1 s)
    # robot time went on by about 1 s (each reading may be a packet old; loaded CI machines)
    assert r.state().t_s - t_r > 0.5


def test_the_arms_state_is_reported_while_it_moves(sim, robot_factory):
    """`state_during_move` (a campaign records them): states between the two poses, moving,
    at most every `state_during_move_every_s` of controller time."""
    r = robot_factory("127.0.0.21")
    r.connect()
    r.move_joints(QA, 1.0, 2.0)
    seen = []
    r.state_during_move = seen.append
    r.move_joints(QB, 1.0, 2.0)
    r.state_during_move = None
    moving = [s for s in seen if np.max(np.abs(s.qd_rad_s)) > 0.05]
    assert len(moving) >= 5, len(seen)
    lo, hi = np.minimum(QA, QB) - 1e-3, np.maximum(QA, QB) + 1e-3
    assert all(np.all((s.q_rad >= lo) & (s.q_rad <= hi)) for s in seen)
    dt = np.diff([s.t_s for s in seen])
    assert np.all(dt >= r.state_during_move_every_s - 1e-9), dt.min()


def test_an_abort_stops_a_move_on_the_way(sim, robot_factory):
    """A campaign's abort flag (`abort_requested`) turning true during a move sends stopJ at
    once: the arm stops between the two poses. Until 2026-11-26 a Ctrl-C waited for the move to
    reach its target (seconds at the campaign's speed) before the robot was stopped."""
    r = robot_factory("127.0.0.21")
    r.connect()
    r.move_joints(QA, 1.0, 2.0)
    flag = threading.Event()
    r.abort_requested = flag.is_set
    timer = threading.Timer(0.2, flag.set)  # 2 s of robot time into a 7 s move
    timer.start()
    try:
        with pytest.raises(MoveAborted) as ei:
            r.move_joints(QB, 0.1, 1.0)
    finally:
        timer.cancel()
    assert "move stopped by an abort" in str(ei.value) and "stopJ failed" not in str(ei.value)
    r.abort_requested = None
    r.sleep(1.0)  # the arm decelerates and stays where it stopped
    q = np.array(sim.state()["q_rad"])
    assert np.max(np.abs(q - QB)) > 0.3 and np.max(np.abs(q - QA)) > 0.05
    assert np.max(np.abs(r.state().qd_rad_s)) < 1e-3


def _refused_before_anything_moves(sp, host: str, model: str, **kw) -> str:
    """Connect with `--model model`: WrongRobotModel in one line naming the host, the arm not
    moved, no script uploaded. Returns the message."""
    r = UrRobot(host, time_scale=TS, model=model, **kw)
    try:
        with pytest.raises(WrongRobotModel) as ei:
            r.connect()
    finally:
        r.close()
    msg = str(ei.value)
    assert "\n" not in msg and host in msg
    st = sp.state()
    assert st["moves"] == 0 and st["stats"]["script_uploads"] == 0
    return msg


def _dashboard_answer(host: str, command: str) -> str:
    with socket.create_connection((host, 29999), timeout=5) as s, s.makefile("rwb") as f:
        f.readline()  # the greeting
        f.write(command.encode() + b"\n")
        f.flush()
        return f.readline().decode().rstrip("\n")


def test_an_e_series_controller_is_refused_for_a_cb3_model():
    """The dashboard names the family only ("UR5" for a CB3 UR5 and a UR5e alike): the driver
    tells the generations apart by the software version, over the real client, before anything
    moves. Until 2026-11-26 a UR10e passed as `--model ur10` (the CB3 arm, 53 mm lower
    shoulder)."""
    with SimProcess("127.0.0.36", time_scale=TS) as sp:  # a UR5e: PolyScope 5
        msg = _refused_before_anything_moves(sp, "127.0.0.36", "ur5")
        assert "runs PolyScope 5.15.0, so the arm is a UR5e, but --model ur5 is a CB3 UR5" in msg
        assert "give --model ur5e" in msg
        assert _dashboard_answer("127.0.0.36", "is in remote control") == "true"


def test_speed_limit_enforced_on_ur10():
    """UR10 base/shoulder are limited to 120 deg/s: a 3 rad/s moveJ cruises at 2.094 rad/s."""
    with SimProcess("127.0.0.24", robot="ur10", time_scale=TS) as sp:
        rr = rtde_receive.RTDEReceiveInterface("127.0.0.24", -1.0, ["actual_qd"])
        rc = rtde_control.RTDEControlInterface("127.0.0.24")
        try:
            target = np.array(sp.state()["q_rad"]) + np.array([2.5, 0, 0, 0, 0, 0])
            assert rc.moveJ(target.tolist(), 3.0, 10.0, True)
            peak = 0.0
            t_end = time.monotonic() + 0.4  # the move takes ~1.4 s of robot time
            while time.monotonic() < t_end:
                peak = max(peak, abs(rr.getActualQd()[0]))
                time.sleep(0.002)
            assert 1.9 < peak <= 2 * np.pi / 3 + 1e-9
        finally:
            rc.disconnect()
            rr.disconnect()


def test_a_controller_of_another_arm_is_refused_before_anything_moves():
    """A UR10 controller and `--model ur5e` (the default): the driver asks the dashboard which
    arm it is and refuses in one line before powering, uploading or moving anything; with
    `--model ur10` it connects. Until 2026-11-26 the simulator answered "UR5" whatever its arm
    and the driver never asked: a UR10 campaign was planned and envelope-checked with UR5e
    kinematics (5 recorded postures put the SMR 39 mm above the envelope box)."""
    with SimProcess("127.0.0.31", robot="ur10", time_scale=TS) as sp:
        db = dashboard_client.DashboardClient("127.0.0.31")
        db.connect()
        try:
            assert db.getRobotModel() == "UR10"
            assert db.polyscopeVersion().startswith("3.")  # a CB3 controller
        finally:
            db.disconnect()
        # commands of e-Series software only are unknown to a CB3 (the simulator said "true")
        for cmd in ("is in remote control", "get operational mode"):
            assert _dashboard_answer("127.0.0.31", cmd) == f"could not understand: '{cmd}'"
        warned: list[str] = []
        msg = _refused_before_anything_moves(sp, "127.0.0.31", "ur5e", on_warning=warned.append)
        assert "the controller says it is a UR10 but --model is ur5e" in msg
        assert "give --model ur10" in msg
        r = UrRobot("127.0.0.31", time_scale=TS, model="ur10", on_warning=warned.append)
        try:
            r.connect()
            assert r.controller_model == "UR10" and r.controller_version == "3.15.8"
            r.move_joints(QA, 1.0, 2.0)
            assert np.max(np.abs(r.state().q_rad - QA)) < 1e-4
        finally:
            r.close()
        assert warned == []
        # a powered-off arm: what the operator does, not a Python argument
        db = dashboard_client.DashboardClient("127.0.0.31")
        db.connect()
        try:
            db.powerOff()
        finally:
            db.disconnect()
        r = UrRobot("127.0.0.31", time_scale=TS, model="ur10")
        try:
            with pytest.raises(DeviceError) as ei:
                r.connect()
        finally:
            r.close()
        msg = str(ei.value)
        assert "POWER_OFF" in msg and "on the teach pendant" in msg
        assert "auto_power_on" not in msg and "\n" not in msg


def test_protective_stop_surfaces_and_unlock_recovers(robot_factory):
    with SimProcess(
        "127.0.0.22", seed=5, time_scale=TS, faults={"protective_stop_at_move": [2]}
    ) as sp:
        r = robot_factory("127.0.0.22")
        r.connect()
        r.move_joints(QA, 1.0, 2.0)
        with pytest.raises(ProtectiveStop):
            r.move_joints(QB, 1.0, 2.0)  # stopped half-way
        st = r.state()
        assert st.safety == "PROTECTIVE_STOP"
        assert np.max(np.abs(st.q_rad - QB)) > 0.05  # did not arrive
        with pytest.raises(ProtectiveStop):
            r.move_joints(QB, 1.0, 2.0)  # refused while stopped
        r.unlock_protective_stop()
        assert r.state().safety == "NORMAL"
        r.move_joints(QB, 1.0, 2.0)
        assert np.max(np.abs(r.state().q_rad - QB)) < 1e-4
        assert sp.state()["stats"]["protective_stops"] == 1


def test_rtde_drop_and_restart_surface_as_device_errors_and_reconnect(robot_factory):
    with SimProcess("127.0.0.23", seed=7, time_scale=TS, faults={"rtde_drop_at_move": [2]}) as sp:
        r = robot_factory("127.0.0.23")
        r.connect()
        r.move_joints(QA, 1.0, 2.0)
        with pytest.raises(DeviceError) as ei:
            r.move_joints(QB, 1.0, 2.0)  # every RTDE connection dropped half-way
        assert not isinstance(ei.value, ProtectiveStop)
        with pytest.raises(DeviceError):
            r.state()
        r.reconnect()
        r.move_joints(QB, 1.0, 2.0)
        assert np.max(np.abs(r.state().q_rad - QB)) < 1e-4

        # 4 s of wall time with every port closed: long enough that a loaded CI machine still
        # sees the drop and the refused reconnect inside the window (0.3 s flaked on 2 workers)
        sp.inject("restart", down_s=40.0)
        t_end = time.monotonic() + 2.0
        with pytest.raises(DeviceError):
            while time.monotonic() < t_end:
                r.state()
                time.sleep(0.01)
        with pytest.raises(DeviceUnreachable):
            r.reconnect()  # still down
        r.reconnect(max_wait_s=120.0)
        r.move_joints(QA, 1.0, 2.0)
        assert np.max(np.abs(r.state().q_rad - QA)) < 1e-4
        stats = sp.state()["stats"]
        assert stats["rtde_drops"] == 1 and stats["restarts"] == 1


def test_unreachable_host_fails_fast_with_one_line():
    r = UrRobot("127.0.0.29", connect_timeout_s=1.0)
    t0 = time.monotonic()
    with pytest.raises(DeviceUnreachable) as ei:
        r.connect()
    assert time.monotonic() - t0 < 3.0
    msg = str(ei.value)
    assert "\n" not in msg and "127.0.0.29" in msg


def test_process_stops_when_parent_closes_stdin():
    sp = SimProcess("127.0.0.25", time_scale=TS).start()
    pid = sp.pid
    sp.stop()
    with pytest.raises(ProcessLookupError):
        for _ in range(50):
            os.kill(pid, 0)
            time.sleep(0.05)


def test_tracker_measures_the_arm_the_controller_moved():
    pytest.importorskip("sim_devices.geocom_tracker")
    from workcell.drivers.serial_tracker import SerialTracker

    with SimProcess("127.0.0.26", seed=11, time_scale=TS, effects="none", with_tracker=True) as sp:
        port = sp.info["tracker_port"]
        assert port and port.startswith("/dev/")
        r = UrRobot("127.0.0.26", time_scale=TS)
        tr = SerialTracker(port)
        try:
            r.connect()
            tr.connect()
            seen = []
            for q in (QA, QB):
                r.move_joints(q, 1.0, 2.0)
                p_true = np.array(sp.command({"cmd": "true_tracker"})["p_tracker"])
                reads = [tr.measure() for _ in range(3)]
                ok = [x.position_m for x in reads if x.status == "ok"]
                assert ok, "no valid tracker reading"
                assert np.linalg.norm(np.mean(ok, axis=0) - p_true) < 2e-4
                seen.append(p_true)
            assert np.linalg.norm(seen[0] - seen[1]) > 0.05  # the SMR moved with the arm
        finally:
            tr.close()
            r.close()


def test_tracker_delays_run_on_the_simulated_clock():
    """A reply 1 simulated second late at --time-scale 20 takes 0.05 s of wall time. Until
    2026-11-26 the simulator handed the tracker 1 / time_scale, so it took 20 s and a tracker
    with slow faults was unusable."""
    from workcell.drivers.serial_tracker import SerialTracker

    faults = {"slow_rate": 1.0, "slow_delay_s": 1.0}
    with SimProcess(
        "127.0.0.32", time_scale=20.0, effects="none", with_tracker=True, tracker_faults=faults
    ) as sp:
        # limits far from the 0.25 s it takes (the bug made each reply take 20 s): a loaded
        # machine's pty round trips took 2.6 s for the five, and one over 1 s
        t = SerialTracker(sp.info["tracker_port"], timeout_s=5.0, retries=0)
        try:
            t0 = time.monotonic()
            t.connect()  # 3 requests
            r = t.measure()  # 2 more
            elapsed = time.monotonic() - t0
            assert r.status == "ok" and t.pop_faults() == []
            assert 5 * 0.05 <= elapsed < 5 * 1.0, elapsed  # under the unscaled delays' 5 s
        finally:
            t.close()


def test_fault_due_half_way_stops_there_even_when_the_tick_is_late():
    """A protective stop scheduled half-way through a move stops the arm half-way even if the
    simulator's tick comes only after the move would have ended (a loaded machine): the old
    behaviour stopped it at the target, which made the protective-stop test flaky under load."""
    from sim_devices.truth import make_truth
    from sim_devices.ur_controller import UrControllerSim
    from sim_devices.world import SimWorld, VirtualClock

    world = SimWorld(make_truth("ur5e", "none", 0), q0=QA)
    ctrl = UrControllerSim(world, "127.0.0.29", faults={"protective_stop_at_move": [1]})
    clock = VirtualClock()
    world.clock = ctrl.clock = clock  # white-box: step time by hand, no sockets opened
    with ctrl.lock:
        ctrl._start_move(np.asarray(QB, float), 1.0, 2.0, False)
    dur = world._traj.duration
    q_half, _ = world._traj.state(0.5 * dur)
    clock.advance(3.0 * dur)  # the next tick comes long after the move's end
    ctrl._tick()
    assert ctrl.stats["protective_stops"] == 1
    q, qd = world.joint_state()
    np.testing.assert_allclose(q, q_half, atol=1e-12)
    assert np.max(np.abs(q - np.asarray(QB))) > 0.05 and np.allclose(qd, 0.0)


@pytest.mark.parametrize("mode, host", [("silent", "127.0.0.27"), ("http", "127.0.0.28")])
def test_a_device_that_is_not_a_ur_controller_is_named_as_such(mode, host):
    """Something else at the robot address (a PLC, a web server) accepts TCP on the UR ports:
    the driver says the device does not answer like a UR controller, in one line, quickly."""
    import socket
    import threading

    servers, conns = [], []

    def serve(srv):
        while True:
            try:
                c, _ = srv.accept()
            except OSError:
                return
            conns.append(c)
            if mode == "http":
                try:
                    c.sendall(b"HTTP/1.0 400 Bad Request\r\n\r\n")
                    c.close()
                except OSError:
                    pass

    for port in (29999, 30001, 30002, 30003, 30004):
        srv = socket.socket()
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind((host, port))
        srv.listen(8)
        servers.append(srv)
        threading.Thread(target=serve, args=(srv,), daemon=True).start()
    try:
        r = UrRobot(host, connect_timeout_s=1.0)
        t0 = time.monotonic()
        with pytest.raises(DeviceError) as ei:
            r.connect()
        assert time.monotonic() - t0 < 5.0
        msg = str(ei.value)
        assert "\n" not in msg and host in msg and "is this the robot controller's address" in msg
        r.close()
    finally:
        for s in servers + conns:
            s.close()


@pytest.mark.parametrize("down", [float("nan"), float("inf"), -1.0])
def test_an_injected_restart_with_no_finite_down_time_is_refused(down):
    """`{"cmd": "inject", "kind": "restart", "down_s": NaN}` on the simulator's stdin was
    answered ok and left the controller down for ever (its down-until time NaN)."""
    from sim_devices.truth import make_truth
    from sim_devices.ur_controller import UrControllerSim
    from sim_devices.world import SimWorld

    world = SimWorld(make_truth("ur5e", "none", 0), q0=QA)
    ctrl = UrControllerSim(world, "127.0.0.29")  # white-box: no sockets opened
    with pytest.raises(ValueError, match="finite time >= 0 s"):
        ctrl.inject("restart", down_s=down)
    assert ctrl.stats["restarts"] == 0


def test_a_control_script_with_a_register_offset_past_the_registers_is_refused():
    """An uploaded rtde_control script with register offset 48 started, and every control
    tick then raised IndexError (120 events in 0.5 s, the event list growing without end)."""
    from sim_devices.truth import make_truth
    from sim_devices.ur_controller import UrControllerSim
    from sim_devices.world import SimWorld

    world = SimWorld(make_truth("ur5e", "none", 0), q0=QA)
    ctrl = UrControllerSim(world, "127.0.0.29")  # white-box: no sockets opened
    prog = b"def rtde_control():\n  reg_offset_int = # int register offset\n  48\nend\n"
    ctrl._program_uploaded("rtde_control", prog)
    assert "register offset 48 is neither 0 nor 24" in ctrl.events[-1][-1]
    assert not ctrl.program_loaded or ctrl.reg_offset != 48
    ctrl._program_uploaded("rtde_control", prog.replace(b"48", b"24"))
    assert ctrl.reg_offset == 24


@pytest.mark.parametrize(
    ("kind", "named"), [("safeguard_stop", "safeguard stop"), ("emergency_stop", "emergency stop")]
)
def test_a_safeguard_or_emergency_stop_is_a_safety_stop_not_a_lost_connection(
    robot_factory, kind, named
):
    """A safeguard stop surfaced as "control program stopped during a move" and an emergency
    stop as a plain device error: the campaign reconnected and moved the arm again by itself,
    once the stop was cleared (a protocol audit). Both are now `SafetyStop`, which names them."""
    from workcell.drivers.protocols import SafetyStop

    with SimProcess("127.0.0.98", seed=5, time_scale=TS) as sp:
        r = robot_factory("127.0.0.98")
        r.connect()
        r.move_joints(QA, 1.0, 2.0)
        threading.Timer(0.1, lambda: sp.inject(kind, down_s=30.0)).start()
        with pytest.raises(SafetyStop, match=named):
            r.move_joints(QB, 0.2, 0.5)  # ~3 s of robot time: stopped on the way
        assert np.max(np.abs(r.state().q_rad - QB)) > 0.01  # did not arrive
        with pytest.raises(SafetyStop, match=named):
            r.move_joints(QB, 1.0, 2.0)  # refused while the stop lasts


def test_the_control_worker_sets_the_rtde_watchdog_so_a_dead_client_stops_the_arm(robot_factory):
    """ur_rtde's control script stops the arm for a client that has gone only when the client
    set its watchdog; the driver set none, so on a real controller a campaign killed mid-move
    left the arm running to its target (the simulator stopped it anyway: a protocol audit).
    The worker now sets it; the simulator stops the program only when one is set."""
    import subprocess
    import sys

    with SimProcess("127.0.0.99", seed=5, time_scale=TS) as sp:
        r = robot_factory("127.0.0.99")
        r.connect()
        r.move_joints(QA, 1.0, 2.0)
        # the driver's worker starts a slow asynchronous move (~35 s of robot time, 3.5 s of
        # wall time: longer than a loaded machine takes to tear the worker down), then dies
        r._rc.call("moveJ", QB.tolist(), 0.02, 0.1, True)
        time.sleep(0.05)
        r._rc.kill()
        deadline = time.monotonic() + 3.0
        while sp.state()["stats"]["watchdog_stops"] < 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert sp.state()["stats"]["watchdog_stops"] >= 1, "the arm was not stopped"
        q = np.array(sp.state()["q_rad"])
        time.sleep(0.3)  # 3 s of robot time
        assert np.max(np.abs(np.array(sp.state()["q_rad"]) - q)) < 1e-9, "the arm still moves"
        assert np.max(np.abs(q - QB)) > 0.01, "the arm ran on to its target"
        r.close()

    with SimProcess("127.0.0.99", seed=5, time_scale=TS) as sp:
        # a client that sets no watchdog: its program goes on when it has gone, as on hardware
        code = (
            "import os, rtde_control\n"
            "rc = rtde_control.RTDEControlInterface('127.0.0.99')\n"
            f"rc.moveJ({QA.tolist()}, 1.0, 2.0)\n"
            f"rc.moveJ({QB.tolist()}, 0.2, 0.5, True)\n"
            "os._exit(0)\n"
        )
        subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
        t_end = time.monotonic() + 5.0
        while np.max(np.abs(np.array(sp.state()["q_rad"]) - QB)) > 1e-4:
            assert time.monotonic() < t_end, "the move did not run on without a watchdog"
            time.sleep(0.05)
        assert sp.state()["stats"]["watchdog_stops"] == 0


def test_a_second_client_does_not_take_the_arm_from_the_first(robot_factory):
    """A second campaign on a controller another one drives uploaded its own control script:
    it ended the first's program mid-campaign and failed itself (crash audit). A program
    running at a driver's first connect is another client's: refused in one line, the first
    campaign goes on; once it has closed, the second connects."""
    with SimProcess("127.0.0.95", seed=5, time_scale=TS) as sp:
        first, second = robot_factory("127.0.0.95"), robot_factory("127.0.0.95")
        first.connect()
        first.move_joints(QA, 1.0, 2.0)
        with pytest.raises(DeviceError, match="a program is running on the controller"):
            second.connect()
        first.move_joints(QB, 1.0, 2.0)  # undisturbed
        assert np.max(np.abs(first.state().q_rad - QB)) < 1e-4
        assert sp.state()["stats"]["script_uploads"] == 1
        first.close()
        second.connect()
        second.move_joints(QA, 1.0, 2.0)
        assert np.max(np.abs(second.state().q_rad - QA)) < 1e-4


def test_a_reconnect_does_not_take_the_arm_from_a_client_moving_it(robot_factory):
    """A driver's reconnect uploaded its script whatever ran, so a campaign whose link had
    dropped took the arm from another client mid-move (a review). A program moving the arm
    at a reconnect is refused; the other client's move arrives."""
    with SimProcess("127.0.0.94", seed=5, time_scale=TS) as sp:
        a, b = robot_factory("127.0.0.94"), robot_factory("127.0.0.94")
        a.connect()
        a.move_joints(QA, 1.0, 2.0)
        a._kill_control()  # its worker gone: its program stops (watchdog)
        b.connect()
        moved = []
        # ~30 s of robot time (3 s of wall time): still moving after the 1.5 s wait
        t = threading.Thread(target=lambda: moved.append(b.move_joints(QB, 0.02, 0.1)))
        t.start()
        time.sleep(0.1)
        with pytest.raises(DeviceError, match="a program is running on the controller and moving"):
            a.reconnect()
        t.join(30.0)
        assert moved == [None], "the other client's move did not arrive"
        assert np.max(np.abs(np.array(sp.state()["q_rad"]) - QB)) < 1e-4
