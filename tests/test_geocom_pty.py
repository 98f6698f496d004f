"""SerialTracker against the simulated GeoCOM instrument over a real pseudo-terminal."""

from __future__ import annotations

import math
import os
import re
import sys
import time

import numpy as np
import pytest

from sim_devices.geocom_tracker import SimGeoComTracker
from workcell.drivers import geocom as gc
from workcell.drivers.protocols import DeviceError, DeviceUnreachable, OtherInstrument, Tracker
from workcell.drivers.serial_tracker import SerialTracker

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="needs a POSIX pty")

TIMEOUT_S = 0.25
# where no time-out is expected and the faults are compared exactly: a reply from the simulated
# instrument took over 0.25 s on a loaded machine, a `timeout` fault the test did not expect
CLEAN_TIMEOUT_S = 2.0


class World:
    """Stands in for the simulated workcell: a new SMR position on every measurement."""

    def __init__(self, seed: int = 1) -> None:
        self.rng = np.random.default_rng(seed)
        self.produced: list[np.ndarray] = []
        self.status = "ok"

    def __call__(self) -> tuple[np.ndarray, str]:
        p = self.rng.uniform([-3.0, -3.0, -1.0], [3.0, 3.0, 2.0])
        self.produced.append(p)
        return p, self.status


@pytest.fixture
def world() -> World:
    return World()


@pytest.fixture
def sim(world: World):
    s = SimGeoComTracker(world, time_scale=1.0).start()
    yield s
    s.stop()


@pytest.fixture
def tracker(sim: SimGeoComTracker):
    t = SerialTracker(sim.port, timeout_s=TIMEOUT_S, retries=2)
    t.connect()
    yield t
    t.close()


def _assert_reading_is_latest(reading, world: World) -> None:
    assert reading.status == "ok"
    np.testing.assert_allclose(reading.position_m, world.produced[-1], rtol=0, atol=1e-12)


def test_connect_and_measure(sim: SimGeoComTracker, tracker: SerialTracker, world: World) -> None:
    assert isinstance(tracker, Tracker)
    assert sim.port.startswith("/dev/")
    assert tracker.instrument_name == sim.instrument_name
    assert tracker.precision == 15
    for _ in range(20):
        r = tracker.measure()
        _assert_reading_is_latest(r, world)
        rng_m = np.linalg.norm(world.produced[-1])
        np.testing.assert_allclose(r.sigma_m, np.full(3, (15e-6 + 6e-6 * rng_m) / 4.0))
        assert r.extra["rc"] == 0 and r.extra["faults"] == 0
    assert len(world.produced) == 20
    assert tracker.pop_faults() == []


def test_reconnect_on_a_live_port(tracker: SerialTracker, world: World) -> None:
    tracker.reconnect()
    _assert_reading_is_latest(tracker.measure(), world)


def test_connect_reads_the_serial_number(sim: SimGeoComTracker, tracker: SerialTracker) -> None:
    assert tracker.serial_number == sim.serial_number == 900001


@pytest.mark.parametrize("serial_number", [900001, 900002])
def test_a_reconnect_must_reach_the_same_instrument(
    sim: SimGeoComTracker, tracker: SerialTracker, world: World, serial_number: int
) -> None:
    """The adapter re-plugged and the OS gives its port name to whatever answers: the same
    tracker (serial number) measures on; another one is refused and the port left closed."""
    other = SimGeoComTracker(world, time_scale=1.0, serial_number=serial_number).start()
    try:
        sim.stop()
        tracker.port = other.port
        if serial_number == sim.serial_number:
            tracker.reconnect()
            _assert_reading_is_latest(tracker.measure(), world)
            return
        with pytest.raises(OtherInstrument) as e:
            tracker.reconnect()
        msg = str(e.value)
        assert "serial number 900002" in msg and "not serial number 900001" in msg, msg
        assert "\n" not in msg and not tracker.is_connected
        with pytest.raises(DeviceError, match="not connected"):
            tracker.measure()
    finally:
        other.stop()


def test_time_scale_speeds_up_simulated_delays(world: World) -> None:
    # every reply 1 simulated second late, simulated time 10x faster: 0.1 s wall per reply
    faults = {"slow_rate": 1.0, "slow_delay_s": 1.0}
    with SimGeoComTracker(world, faults=faults, time_scale=10.0) as s:
        t = SerialTracker(s.port, timeout_s=CLEAN_TIMEOUT_S)
        t.connect()
        t.pop_faults()
        t0 = time.monotonic()
        _assert_reading_is_latest(t.measure(), world)
        assert 0.2 <= time.monotonic() - t0 < 2.5  # unscaled: 3 replies of 1 s each
        assert t.pop_faults() == []
        t.close()


def test_sim_rejects_bad_fault_settings(world: World) -> None:
    with pytest.raises(ValueError, match="unknown fault keys"):
        SimGeoComTracker(world, faults={"garbage": 0.1})
    with pytest.raises(ValueError, match="must be in"):
        SimGeoComTracker(world, faults={"drop_rate": 1.5})
    with pytest.raises(ValueError, match="time_scale"):
        SimGeoComTracker(world, time_scale=0.0)
    with pytest.raises(ValueError, match="unknown fault kind"):
        SimGeoComTracker(world).inject("explode")


def test_low_instrument_precision_is_raised_on_connect(world: World) -> None:
    with SimGeoComTracker(world, precision=4) as s:
        t = SerialTracker(s.port, timeout_s=CLEAN_TIMEOUT_S)
        t.connect()
        assert (t.precision, s.precision) == (15, 15)
        _assert_reading_is_latest(t.measure(), world)
        t.close()


def test_crc_mode(sim: SimGeoComTracker, world: World) -> None:
    t = SerialTracker(sim.port, timeout_s=CLEAN_TIMEOUT_S, use_crc=True)
    t.connect()
    _assert_reading_is_latest(t.measure(), world)
    assert t.pop_faults() == []
    assert sim.stats["bad_request_crc"] == 0
    t.close()


@pytest.mark.parametrize(
    ("world_status", "expected"),
    [("beam_broken", "beam_broken"), ("out_of_range", "beam_broken"), ("error", "error")],
)
def test_world_status_maps_to_reading_status(
    tracker: SerialTracker, world: World, world_status: str, expected: str
) -> None:
    world.status = world_status
    r = tracker.measure()
    assert r.status == expected
    assert np.all(np.isnan(r.position_m)) and np.all(np.isnan(r.sigma_m))
    world.status = "ok"
    _assert_reading_is_latest(tracker.measure(), world)


def test_injected_beam_break_is_angle_ok_no_distance(
    sim: SimGeoComTracker, tracker: SerialTracker, world: World
) -> None:
    sim.inject("beam_break")
    r = tracker.measure()
    assert r.status == "beam_broken"
    assert r.extra["rc"] == 1285 and r.extra["rc_name"] == "GRC_TMC_ANGLE_OK"
    assert tracker.pop_faults() == []  # a beam break is an answer, not a link fault
    _assert_reading_is_latest(tracker.measure(), world)


def test_beam_break_rate_matches_injected_count(world: World) -> None:
    with SimGeoComTracker(world, faults={"beam_break_rate": 0.3}, seed=3) as s:
        t = SerialTracker(s.port, timeout_s=CLEAN_TIMEOUT_S)
        t.connect()
        statuses = [t.measure().status for _ in range(60)]
        t.close()
    assert statuses.count("beam_broken") == s.stats["beam_break"]
    assert 0 < statuses.count("beam_broken") < 60


@pytest.mark.parametrize("kind", ["garbage_before", "garbage_instead"])
def test_garbage_resyncs_and_next_measurement_is_clean(
    sim: SimGeoComTracker, tracker: SerialTracker, world: World, kind: str
) -> None:
    sim.inject(kind)
    r = tracker.measure()
    _assert_reading_is_latest(r, world)
    kinds = [k for k, _ in tracker.pop_faults()]
    assert "resync" in kinds
    assert "garbage" in kinds or "timeout" in kinds  # 'instead' may carry no line end
    r = tracker.measure()
    _assert_reading_is_latest(r, world)
    assert tracker.pop_faults() == []


def test_dropped_line_times_out_and_retries(
    sim: SimGeoComTracker, tracker: SerialTracker, world: World
) -> None:
    sim.inject("drop")
    t0 = time.monotonic()
    r = tracker.measure()
    elapsed = time.monotonic() - t0
    _assert_reading_is_latest(r, world)
    kinds = [k for k, _ in tracker.pop_faults()]
    assert kinds[0] == "timeout" and "resync" in kinds
    assert elapsed >= TIMEOUT_S
    assert sim.stats["drop"] == 1


def test_slow_reply_late_answer_is_skipped_by_transaction_id(
    sim: SimGeoComTracker, tracker: SerialTracker, world: World
) -> None:
    sim.faults["slow_delay_s"] = 2 * TIMEOUT_S
    sim.inject("slow")
    r = tracker.measure()
    _assert_reading_is_latest(r, world)
    kinds = [k for k, _ in tracker.pop_faults()]
    assert "timeout" in kinds and "stale_reply" in kinds
    # a slow reply within the time-out is no fault at all
    sim.faults["slow_delay_s"] = 0.3 * TIMEOUT_S
    sim.inject("slow")
    _assert_reading_is_latest(tracker.measure(), world)
    assert tracker.pop_faults() == []


def test_silent_instrument_gives_device_error(
    sim: SimGeoComTracker, tracker: SerialTracker
) -> None:
    sim.inject("drop", 1000)
    t0 = time.monotonic()
    # a measurement asks first whether the instrument follows the target
    with pytest.raises(DeviceError, match="is silent: no reply to MOT_ReadLockStatus") as ei:
        tracker.measure()
    assert not isinstance(ei.value, DeviceUnreachable)
    # one time-out on the request, then retries + 1 = 3 COM_NullProc tries
    assert time.monotonic() - t0 >= 4 * TIMEOUT_S
    kinds = [k for k, _ in tracker.pop_faults()]
    assert kinds == ["timeout", "resync_failed", "gave_up"]


def test_persistently_garbled_replies_give_device_error_after_retries(
    sim: SimGeoComTracker, tracker: SerialTracker
) -> None:
    # every reply to TMC_DoMeasure garbled while COM_NullProc answers: the link works, the
    # request is re-sent `retries` times, then DeviceError
    sim.inject("garbage_before", 3, rpc=2008)
    with pytest.raises(DeviceError, match="no valid reply to TMC_DoMeasure after 3 attempts"):
        tracker.measure()
    kinds = [k for k, _ in tracker.pop_faults()]
    assert kinds.count("garbage") == 3 and kinds[-1] == "gave_up"


def test_vanish_gives_device_unreachable_with_clear_message(
    sim: SimGeoComTracker, tracker: SerialTracker, world: World
) -> None:
    _assert_reading_is_latest(tracker.measure(), world)
    port = sim.port
    sim.vanish()
    assert not os.path.exists(port)
    with pytest.raises(DeviceUnreachable) as ei:
        tracker.measure()
    msg = str(ei.value)
    assert port in msg and "vanished" in msg and "reconnect" in msg
    assert not tracker.is_connected
    with pytest.raises(DeviceUnreachable, match="lost earlier and is not back"):
        tracker.measure()
    with pytest.raises(DeviceUnreachable, match="cannot be opened"):
        tracker.reconnect()


def test_vanish_after_n_requests(world: World) -> None:
    # connect = 11 requests (NullProc, GetDoublePrecision, GetInstrumentName, GetInstrumentNo,
    # the 3 setup queries, ATR and LOCK modes, FineAdjust, LockIn), a measure = 3 (the lock
    # status, DoMeasure, GetCoordinate)
    with SimGeoComTracker(world, faults={"vanish_after": 18}) as s:
        t = SerialTracker(s.port, timeout_s=CLEAN_TIMEOUT_S)
        t.connect()
        _assert_reading_is_latest(t.measure(), world)
        _assert_reading_is_latest(t.measure(), world)
        with pytest.raises(DeviceUnreachable, match="vanished"):
            t.measure()
        assert s.vanished


def test_unopenable_and_non_geocom_ports_are_unreachable(tmp_path) -> None:
    with pytest.raises(DeviceUnreachable, match="cannot be opened"):
        SerialTracker(str(tmp_path / "no-such-tty"), timeout_s=0.05).connect()
    # loop:// echoes our requests back: a line, but nobody answering GeoCOM
    t = SerialTracker("loop://", timeout_s=0.05, retries=0)
    with pytest.raises(DeviceUnreachable, match="no GeoCOM answer"):
        t.connect()
    assert not t.is_connected


def test_random_faults_never_mix_up_measurements(world: World) -> None:
    timeout_s = 0.1
    faults = {
        "slow_rate": 0.05,
        "slow_delay_s": 2 * timeout_s,
        "garbage_rate": 0.05,
        "drop_rate": 0.05,
        "beam_break_rate": 0.05,
    }
    with SimGeoComTracker(world, faults=faults, seed=11) as s:
        t = SerialTracker(s.port, timeout_s=timeout_s, retries=3, measure_wait_s=0.0)
        t.connect()
        statuses = []
        for _ in range(60):
            try:
                r = t.measure()
            except DeviceError:
                statuses.append("device_error")
                continue
            statuses.append(r.status)
            if r.status == "ok":
                _assert_reading_is_latest(r, world)
        faults_seen = {k for k, _ in t.pop_faults()}
        t.close()
    assert statuses.count("ok") >= 40
    injected = s.stats["garbage"] + s.stats["drop"] + s.stats["slow"]
    assert injected > 0 and "resync" in faults_seen


# ----------------------------------------------------------------------------- geocompy


@pytest.mark.parametrize("checksum", [False, True])
def test_geocompy_client_reads_a_coordinate(
    sim: SimGeoComTracker, world: World, checksum: bool
) -> None:
    from geocompy.communication import open_serial
    from geocompy.geo import GeoCom
    from geocompy.geo.gctypes import GeoComCode

    with open_serial(sim.port, speed=115200, timeout=2) as conn:
        tps = GeoCom(conn, checksum=checksum)  # NullProc, precision sync, name, versions
        assert tps.precision == 15
        assert tps.csv.get_instrument_name().params == sim.instrument_name
        assert tps.csv.get_serial_number().params == sim.serial_number
        assert tps.tmc.do_measurement().error == GeoComCode.OK
        resp = tps.tmc.get_coordinate(wait=1)
        assert resp.error == GeoComCode.OK
        coord, t_ms, _coord_cont, _t_cont = resp.params
        np.testing.assert_allclose(
            [coord.e, coord.n, coord.h], world.produced[-1], rtol=0, atol=1e-12
        )
        assert t_ms >= 0
        sim.inject("beam_break")
        assert tps.tmc.do_measurement().error == GeoComCode.OK
        assert tps.tmc.get_coordinate(wait=1).error == GeoComCode.TMC_ANGLE_OK
    assert sim.stats["bad_request"] == 0 and sim.stats["bad_request_crc"] == 0


# ----------------------------------------------------------------------------- odd instruments


class _OddInstrument:
    """A GeoCOM-ish responder on a pty that misbehaves in one way (`mode`):
    `wrong_trid` answers every request with another transaction id, `no_lf` answers without a
    line end, `flood` answers 5000 bytes without a line end, `coord` answers TMC_GetCoordinate with the coordinate text `coord`."""

    def __init__(self, mode: str, coord: str = "1.0") -> None:
        import threading
        import tty

        self.mode, self.coord = mode, coord
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._serve, daemon=True)
        self._t.start()

    def _reply(self, rpc: int, trid: int) -> bytes:
        body = "0"
        if rpc == 108:
            body = "0,15"
        elif rpc == 5004:
            body = '0,"ODD"'
        elif rpc == 2082:
            c = self.coord
            body = f"0,{c},{c},{c},5,{c},{c},{c},5"
        if self.mode == "flood":  # more than a line's worth (4096 bytes) without a line end
            return b"A" * 5000
        if self.mode == "wrong_trid":
            trid = trid % 32767 + 7
        end = b"" if self.mode == "no_lf" else b"\r\n"
        return f"%R1P,0,{trid}:{body}".encode() + end

    def _serve(self) -> None:
        import re
        import select

        buf = b""
        while not self._stop.is_set():
            r, _, _ = select.select([self.master], [], [], 0.02)
            if not r:
                continue
            try:
                buf += os.read(self.master, 4096)
            except OSError:
                continue
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                m = re.match(rb"%R1Q,(\d+),(\d+):", line.strip())
                if m:
                    os.write(self.master, self._reply(int(m.group(1)), int(m.group(2))))

    def close(self) -> None:
        self._stop.set()
        self._t.join(2.0)
        for fd in (self.master, self.slave):
            os.close(fd)


@pytest.mark.parametrize(
    "mode, what",
    [
        ("wrong_trid", "another transaction id"),
        ("no_lf", "without a line end (LF)"),
        ("flood", "without a line end (LF)"),  # escaped as a ValueError until 2026-11-28
    ],
)
def test_an_instrument_answering_wrongly_is_not_called_silent(mode: str, what: str) -> None:
    """Replies that are not GeoCOM answers to our requests (another transaction id, no line end)
    are told apart from silence: until 2026-11-26 both read "is silent ... check the instrument
    is on", which sends the operator to the power switch of an instrument that is talking."""
    odd = _OddInstrument(mode)
    try:
        t = SerialTracker(odd.port, timeout_s=0.1, retries=1)
        with pytest.raises(DeviceUnreachable) as ei:
            t.connect()
        msg = str(ei.value)
        assert "\n" not in msg and odd.port in msg
        assert (
            "answers, but not with GeoCOM replies to our requests" in msg
            or "something answers on the port, but not GeoCOM" in msg
        ) and what in msg
        assert "silent" not in msg and "is on" not in msg
    finally:
        odd.close()


def test_silence_is_still_called_silent(world: World) -> None:
    with SimGeoComTracker(world, faults={"drop_rate": 1.0}) as s:
        t = SerialTracker(s.port, timeout_s=0.1, retries=1)
        with pytest.raises(DeviceUnreachable, match="is silent.*check the instrument is on"):
            t.connect()


@pytest.mark.parametrize(
    "p, why",
    [
        ((1e300, 1e300, 1e300), "1.732e\\+300 m from the instrument"),
        ((150.0, 160.0, 0.0), "219.3 m"),
    ],
)
def test_a_coordinate_no_tracker_measures_is_a_bad_reading(
    world: World, p: tuple, why: str
) -> None:
    """A fake tracker answering 1e300 had 7 poses recorded with that value. A coordinate beyond
    200 m (no laser tracker reaches 160 m; the recording checks' bound) is a bad reading: status
    not ok, the reason in `extra` and in a `bad_reading` fault; the next good one is ok."""
    world.status = "ok"
    with SimGeoComTracker(lambda: (np.array(p), "ok"), time_scale=1.0) as s:
        t = SerialTracker(s.port, timeout_s=CLEAN_TIMEOUT_S)
        t.connect()
        r = t.measure()
        assert r.status == "error" and np.all(np.isnan(r.position_m))
        assert "no laser tracker measures beyond 200 m" in r.extra["message"]
        assert re.search(why, r.extra["message"]), r.extra["message"]
        assert [k for k, _ in t.pop_faults()] == ["bad_reading"]
        s.measure_fn = world
        _assert_reading_is_latest(t.measure(), world)
        t.close()


def test_a_coordinate_too_large_for_a_float_is_a_bad_reading() -> None:
    """'1e999' is well-formed GeoCOM that overflows to inf: a bad reading (not finite), not a
    garbled line re-requested three times."""
    odd = _OddInstrument("coord", coord="1e999")
    try:
        t = SerialTracker(odd.port, timeout_s=CLEAN_TIMEOUT_S)
        t.connect()
        r = t.measure()
        assert r.status == "error" and np.all(np.isnan(r.position_m))
        assert "not finite" in r.extra["message"]
        assert [k for k, _ in t.pop_faults()] == ["bad_reading"]
        t.close()
    finally:
        odd.close()


def test_sim_fault_settings_are_bounded(world: World) -> None:
    """garbage_len 1e12 made the simulator draw a terabyte of garbage; a non-finite or huge
    slow_delay_s killed its server thread (a wait beyond threading's limit)."""
    for faults, match in [
        ({"garbage_len": 1e12}, r"garbage_len must be 1\.\.4096"),
        ({"garbage_len": 2.5}, "garbage_len must be a whole number"),
        ({"garbage_mode": "sideways"}, "garbage_mode must be"),
        ({"slow_delay_s": float("nan")}, "slow_delay_s must be a finite number"),
        ({"slow_delay_s": 1e12}, r"slow_delay_s must be in \[0, 3600\]"),
        ({"garbage_rate": "often"}, "garbage_rate must be a finite number"),
        ({"vanish_after": 0}, "vanish_after must be >= 1"),
    ]:
        with pytest.raises(ValueError, match=match):
            SimGeoComTracker(world, faults=faults)
    faults = {"garbage_rate": 1.0, "garbage_mode": "before", "garbage_len": 4096}
    assert SimGeoComTracker(world, faults=faults).faults["garbage_mode"] == "before"


def test_a_clean_resync_answer_to_com_nullproc_is_an_answer(world: World) -> None:
    """A noisy line (30 % garbled replies, seed 3): each COM_NullProc of the connect check was
    garbled while the resync's COM_NullProc between them got a clean reply, and the driver gave
    up with "no GeoCOM answer ... something answers on the port, but not GeoCOM". The resync's
    clean reply to the very call being made now counts."""
    faults = {"garbage_rate": 0.3, "drop_rate": 0.0, "slow_rate": 0.0}
    with SimGeoComTracker(world, faults=faults, seed=3, time_scale=50) as s:
        t = SerialTracker(s.port, timeout_s=0.2)
        try:
            t.connect()
            assert t.instrument_name == s.instrument_name
            assert any(k == "resync" for k, _ in t.pop_faults())
        finally:
            t.close()


def test_a_stale_coordinate_is_refused_not_averaged(
    sim: SimGeoComTracker, tracker: SerialTracker, world: World
) -> None:
    """An instrument that answers TMC_DoMeasure with GRC_OK but measures nothing returns its
    previous coordinate again, CoordTime and all. Read as a new reading it would be averaged as
    an independent one (or, at the next pose, recorded as that pose's position). It is refused:
    status not ok, a `stale_reading` fault naming the repeated CoordTime; the next real
    measurement is read as usual."""
    first = tracker.measure()
    _assert_reading_is_latest(first, world)
    sim.inject("stale")
    r = tracker.measure()
    assert sim.stats["stale"] == 1 and len(world.produced) == 1  # nothing new was measured
    assert r.status == "error" and np.all(np.isnan(r.position_m))
    assert r.extra["rc_name"] == "stale_reading"
    assert r.extra["instrument_time_ms"] == first.extra["instrument_time_ms"]
    faults = tracker.pop_faults()
    assert [k for k, _ in faults] == ["stale_reading"]
    assert f"CoordTime {first.extra['instrument_time_ms']} ms" in faults[0][1]
    after = tracker.measure()
    _assert_reading_is_latest(after, world)
    assert after.extra["instrument_time_ms"] > first.extra["instrument_time_ms"]


def test_instant_simulated_measurements_never_repeat_a_coordtime(world: World) -> None:
    """With instantaneous simulated delays many measurements fall in one millisecond; each still
    gets its own CoordTime (a measurement takes time), so none is taken for a stale repeat."""
    with SimGeoComTracker(world, time_scale=math.inf) as s:
        t = SerialTracker(s.port, timeout_s=CLEAN_TIMEOUT_S)
        t.connect()
        times = []
        for _ in range(30):
            r = t.measure()
            _assert_reading_is_latest(r, world)
            times.append(r.extra["instrument_time_ms"])
        t.close()
    assert np.all(np.diff(times) >= 1), times
    assert t.pop_faults() == []


class _NoClockSim(SimGeoComTracker):
    """An instrument that keeps no measurement time: CoordTime is always 0."""

    def _get_coordinate(self, req):
        rc0, rc, v = super()._get_coordinate(req)
        if len(v) == 8:
            v = (v[0], v[1], v[2], 0, v[4], v[5], v[6], 0)
        return rc0, rc, v


def test_an_instrument_without_coordtime_still_gives_new_readings(world: World) -> None:
    """The same CoordTime with new coordinates is a new measurement (an instrument that keeps no
    clock): only the same time and the very same coordinates are a stale repeat."""
    with _NoClockSim(world, time_scale=1.0) as s:
        t = SerialTracker(s.port, timeout_s=CLEAN_TIMEOUT_S)
        t.connect()
        for _ in range(5):
            r = t.measure()
            _assert_reading_is_latest(r, world)
            assert r.extra["instrument_time_ms"] == 0
        s.inject("stale")
        assert t.measure().extra["rc_name"] == "stale_reading"
        t.close()


def test_the_driver_reads_the_setup_and_locks_onto_the_target(
    sim: SimGeoComTracker, tracker: SerialTracker, world: World
) -> None:
    """Nothing aimed or locked the instrument onto the SMR (a GeoCOM instrument measures where
    it points: on hardware every pose after a move would have been a beam break), and the
    corrections it applies (prism constant, ppm) were neither read nor recorded (a protocol
    audit). Now connect turns ATR and LOCK on and locks in, every measurement checks the lock
    and locks in again once when it was lost, and the setup is read."""
    assert tracker.lock == "locked" and tracker.lock_mode
    assert tracker.setup == {
        "station_enh_m": [0.0, 0.0, 0.0],
        "instrument_height_m": 0.0,
        "prism_constant_m": 0.0,
        "atm_ppm": 0.0,
    }
    sim.inject("lock_lost", rpc=gc.Rpc.MOT_ReadLockStatus)  # lost, found again at once
    _assert_reading_is_latest(tracker.measure(), world)
    assert sim.stats["lock_lost"] == 1
    sim.inject("lock_lost", rpc=gc.Rpc.MOT_ReadLockStatus)
    sim.inject("lock_lost", rpc=gc.Rpc.AUT_FineAdjust)  # ... and not found: no measurement
    r = tracker.measure()
    assert r.status == "beam_broken" and r.extra["rc_name"] == "not_locked"
    assert np.all(np.isnan(r.position_m))
    _assert_reading_is_latest(tracker.measure(), world)  # found at the next try
    assert not [k for k, _ in tracker.pop_faults() if k == "com_error"]


def test_an_instrument_without_atr_measures_where_it_points_as_before(world: World) -> None:
    """An instrument refusing the lock RPCs (no ATR) is said once and measured as before."""
    with SimGeoComTracker(world) as s:
        real = s._dispatch

        def no_atr(req):
            if req.rpc in (gc.Rpc.AUS_SetUserAtrState, gc.Rpc.AUS_SetUserLockState):
                return gc.Grc.COM_PROC_UNAVAIL, 0, ()
            return real(req)

        s._dispatch = no_atr
        t = SerialTracker(s.port, timeout_s=CLEAN_TIMEOUT_S)
        t.connect()
        assert not t.lock_mode and t.lock.startswith("no target lock")
        _assert_reading_is_latest(t.measure(), world)
        t.close()
