"""A simulated GeoCOM instrument (Leica tracker / total station) behind a pseudo-terminal.

The server owns the master side of a pty (raw mode, so CR/LF pass untouched) and answers GeoCOM
ASCII requests in a background thread; a client opens `.port` (`/dev/pts/N`) like a real serial
port. Served RPCs: COM_NullProc (0), COM_SetDoublePrecision (107), COM_GetDoublePrecision (108),
COM_GetSWVersion (110), TMC_DoMeasure (2008), TMC_GetCoordinate (2082), CSV_GetInstrumentNo
(5003), CSV_GetInstrumentName (5004), CSV_GetSWVersion (5034), the setup queries TMC_GetStation
(2009: at the origin), TMC_GetPrismCorr (2023) and TMC_GetAtmPpm (2151) (both 0), and the target
lock: AUS_SetUserAtrState (18005), AUS_SetUserLockState (18007), AUT_FineAdjust (9037),
AUT_LockIn (9013), MOT_ReadLockStatus (6021); any other RPC gets COM_PROC_UNAVAIL. A request
carrying a CRC is checked (bad -> COM_SRVR_RX_CHECKSUM_ERROR) and
answered with a CRC; a request without one is answered without.

The world is `measure_fn() -> (p_tracker (3,) metres, status)`, called once per TMC_DoMeasure;
it already holds the noise model. Status `ok` -> coordinates with GRC_OK; `beam_broken` ->
TMC_ANGLE_OK (1285, "angles ok, no distance"); `out_of_range` -> TMC_DIST_ERROR (1292);
anything else -> TMC_ANGLE_ERROR (1290). TMC_GetCoordinate without a stored distance (no
DoMeasure yet, or after TMC_CLEAR) also answers TMC_ANGLE_OK.

Faults (`faults` dict; rates are probabilities per request, drawn from `seed`):
    beam_break_rate   a TMC_DoMeasure yields "angles ok, no distance" regardless of the world
    slow_rate         the reply is delayed by slow_delay_s (default 2.0 s)
    slow_delay_s      0..3600 simulated seconds
    garbage_rate      random bytes (1..garbage_len, default 24, at most 4096) go out before the
                      reply (garbage_mode "before"), instead of it ("instead"), or either
                      ("mixed", the default)
    drop_rate         no reply at all (a dropped line)
    vanish_after      after this many requests the pty is closed: the port disappears
    stale_rate        a TMC_DoMeasure answers GRC_OK but measures nothing (kind `stale` below)
`inject(kind, count, rpc=None)` forces a fault on the next `count` requests (of RPC `rpc` only, if
given) for deterministic tests; kinds:
`beam_break`, `slow`, `garbage`, `garbage_before`, `garbage_instead`, `drop`, `vanish`, and
`stale` (a TMC_DoMeasure answers GRC_OK but measures nothing: the next TMC_GetCoordinate returns
the previous measurement with its CoordTime, as an instrument that did not refresh its
coordinate would), and `lock_lost` (give rpc=6021 to lose the lock at the next status read, or
rpc=9037 to make the next fine adjustment find no target).

time_scale: simulated time runs `time_scale` times faster than the wall clock (as
`sim_devices.world.ScaledClock`): a simulated delay d (slow replies, `measure_time_s`) takes
d / time_scale wall seconds, and the instrument clock (CoordTime, ms) advances time_scale ms per
wall ms. `math.inf` makes delays instantaneous. Each new measurement's CoordTime is at least 1 ms
after the one before (a measurement takes time), so instantaneous delays never repeat a CoordTime.
"""

from __future__ import annotations

import errno
import math
import os
import re
import select
import threading
import time
import tty
from collections import Counter
from collections.abc import Callable

import numpy as np

from workcell.drivers import geocom as gc

FAULT_KEYS = frozenset(
    {
        "beam_break_rate",
        "slow_rate",
        "slow_delay_s",
        "garbage_rate",
        "garbage_mode",
        "garbage_len",
        "drop_rate",
        "vanish_after",
        "stale_rate",
    }
)
INJECT_KINDS = frozenset(
    {
        "beam_break",
        "slow",
        "garbage",
        "garbage_before",
        "garbage_instead",
        "drop",
        "vanish",
        "stale",
        "lock_lost",
    }
)
AUT_NO_TARGET = 8710  # GRC_AUT_NO_TARGET: no ATR target in the search window
_MEASURE_PRGS = {
    gc.TmcMeasurePrg.TMC_DEF_DIST,
    gc.TmcMeasurePrg.TMC_TRK_DIST,
    gc.TmcMeasurePrg.TMC_DO_MEASURE,
    gc.TmcMeasurePrg.TMC_RTRK_DIST,
    gc.TmcMeasurePrg.TMC_RED_TRK_DIST,
}
_CLEAR_PRGS = {gc.TmcMeasurePrg.TMC_STOP, gc.TmcMeasurePrg.TMC_CLEAR}
_STATUS_RC = {
    "ok": gc.Grc.OK,
    "beam_broken": gc.Grc.TMC_ANGLE_OK,
    "out_of_range": gc.Grc.TMC_DIST_ERROR,
}
_TRID_RE = re.compile(rb"%R1Q,\d{1,5},(\d{1,10})")


GARBAGE_LEN_MAX = gc.MAX_LINE_BYTES  # a longer burst is dropped by any client as one line
SLOW_DELAY_MAX_S = 3600.0  # simulated seconds


def _number(key: str, v: object, *, integer: bool = False) -> float:
    """A fault setting as a finite number (an integer if `integer`); ValueError naming it."""
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    if not ok or (integer and float(v) != int(v)):
        kind = "a whole number" if integer else "a finite number"
        raise ValueError(f"tracker fault {key} must be {kind}, got {v!r}")
    return int(v) if integer else float(v)


def validate_faults(faults: dict | None) -> dict:
    """The tracker fault settings checked and completed with defaults (module doc); a bad one
    raises ValueError with one line naming it."""
    f = dict(faults or {})
    unknown = set(f) - FAULT_KEYS
    if unknown:
        raise ValueError(f"unknown fault keys {sorted(unknown)}; known: {sorted(FAULT_KEYS)}")
    for key in ("beam_break_rate", "slow_rate", "garbage_rate", "drop_rate", "stale_rate"):
        rate = _number(key, f.get(key, 0.0))
        if not 0.0 <= rate <= 1.0:
            raise ValueError(f"fault rate {key} must be in [0, 1], got {rate!r}")
        f[key] = rate
    f["slow_delay_s"] = _number("slow_delay_s", f.get("slow_delay_s", 2.0))
    if not 0 <= f["slow_delay_s"] <= SLOW_DELAY_MAX_S:
        raise ValueError(
            f"slow_delay_s must be in [0, {SLOW_DELAY_MAX_S:g}] simulated seconds, "
            f"got {f['slow_delay_s']!r}"
        )
    f["garbage_len"] = _number("garbage_len", f.get("garbage_len", 24), integer=True)
    if not 1 <= f["garbage_len"] <= GARBAGE_LEN_MAX:
        raise ValueError(
            f"garbage_len must be 1..{GARBAGE_LEN_MAX} bytes (a GeoCOM line's limit), "
            f"got {f['garbage_len']!r}"
        )
    f["garbage_mode"] = f.get("garbage_mode", "mixed")
    if f["garbage_mode"] not in ("before", "instead", "mixed"):
        raise ValueError(
            f"garbage_mode must be 'before', 'instead' or 'mixed', got {f['garbage_mode']!r}"
        )
    va = f.get("vanish_after")
    if va is not None:
        va = _number("vanish_after", va, integer=True)
        if va < 1:
            raise ValueError(f"vanish_after must be >= 1 request, got {va!r}")
    f["vanish_after"] = va
    return f


_validate_faults = validate_faults  # the old private name


class SimGeoComTracker:
    """GeoCOM server on a pty. Use `.start()`, connect a client to `.port`, `.stop()`."""

    def __init__(
        self,
        measure_fn: Callable[[], tuple[np.ndarray, str]],
        *,
        faults: dict | None = None,
        seed: int = 0,
        time_scale: float = 1.0,
        instrument_name: str = "SIM GeoCOM tracker",
        serial_number: int = 900001,
        precision: int = 15,
        measure_time_s: float = 0.0,
    ) -> None:
        if not time_scale > 0:
            raise ValueError(f"time_scale must be > 0 (inf: no delays), got {time_scale!r}")
        if not 0 <= precision <= 15:
            raise ValueError(f"precision must be in 0..15, got {precision!r}")
        self.measure_fn = measure_fn
        self.faults = validate_faults(faults)
        self.time_scale = float(time_scale)
        self.instrument_name = instrument_name
        self.serial_number = int(serial_number)
        self.precision = int(precision)
        self.measure_time_s = float(measure_time_s)
        self.geocom_version = (1, 50, 0)
        self.firmware_version = (7, 0, 0)
        self.stats: Counter[str] = Counter()
        # ATR/LOCK (AUS_SetUserLockState, AUT_FineAdjust, AUT_LockIn, MOT_ReadLockStatus): the
        # simulated instrument measures the SMR wherever it is, locked or not; the state is
        # what the driver must handle (`inject("lock_lost")`: the lock is lost at the next
        # status read and the next fine adjustment finds no target)
        self._lock_mode = self._fine_adjusted = self._locked = False
        self.errors: list[str] = []  # measure_fn exceptions etc., for tests/diagnosis
        self._rng = np.random.default_rng(seed)
        self._forced: Counter[tuple[str, int | None]] = Counter()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._vanish_req = threading.Event()
        self._vanished = threading.Event()
        self._gone = False
        self._thread: threading.Thread | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._port: str | None = None
        self._stored: tuple[np.ndarray, str, int] | None = None
        self._last_coord_ms: int | None = None  # CoordTime of the last measurement
        self._t0 = time.monotonic()

    # ------------------------------------------------------------------ lifecycle
    @property
    def port(self) -> str:
        if self._port is None:
            raise RuntimeError("SimGeoComTracker not started: call start() first")
        return self._port

    @property
    def vanished(self) -> bool:
        return self._gone

    def start(self) -> SimGeoComTracker:
        if self._thread is not None:
            return self
        master, slave = os.openpty()
        tty.setraw(master)
        tty.setraw(slave)  # no CR/LF translation, no echo, no XON/XOFF
        self._master, self._slave = master, slave
        self._port = os.ttyname(slave)
        self._t0 = time.monotonic()
        self._stop.clear()
        self._vanish_req.clear()
        self._vanished.clear()
        self._thread = threading.Thread(target=self._serve, name="sim-geocom", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout=5.0)
        self._close_fds()

    def vanish(self) -> None:
        """Close the pty now: the client sees an I/O error and `/dev/pts/N` disappears."""
        if self._thread is None or not self._thread.is_alive():
            self._gone = True
            self._close_fds()
            self._vanished.set()
            return
        if threading.current_thread() is self._thread:
            self._do_vanish()
            return
        self._vanish_req.set()
        self._vanished.wait(timeout=5.0)

    def inject(self, kind: str, count: int = 1, *, rpc: int | None = None) -> None:
        """Force a fault kind on the next `count` requests (only those of RPC `rpc` if given)."""
        if kind not in INJECT_KINDS:
            raise ValueError(f"unknown fault kind {kind!r}; known: {sorted(INJECT_KINDS)}")
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count!r}")
        with self._lock:
            self._forced[(kind, None if rpc is None else int(rpc))] += int(count)

    def __enter__(self) -> SimGeoComTracker:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ server thread
    def _close_fds(self) -> None:
        with self._lock:
            fds = [fd for fd in (self._master, self._slave) if fd is not None]
            self._master = self._slave = None
        for fd in fds:
            try:
                os.close(fd)
            except OSError:
                pass

    def _do_vanish(self) -> None:
        self.stats["vanish"] += 1
        self._gone = True  # before the fds close: a client may see the I/O error at once
        self._close_fds()
        self._vanished.set()
        self._stop.set()

    def _serve(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            if self._vanish_req.is_set():
                self._do_vanish()
                return
            master = self._master
            if master is None:
                return
            try:
                ready, _, _ = select.select([master], [], [], 0.05)
                if not ready:
                    continue
                data = os.read(master, 4096)
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EINTR, errno.EAGAIN):
                    time.sleep(0.01)  # no client has the slave open right now
                    continue
                self.errors.append(f"pty read failed: {exc}")
                return
            buf.extend(data)
            while True:
                i = buf.find(b"\n")
                if i < 0:
                    break
                line = bytes(buf[:i]).strip(b"\r")
                del buf[: i + 1]
                if line:
                    self._handle(line)
                if self._stop.is_set():
                    return
            if len(buf) > gc.MAX_LINE_BYTES:
                buf.clear()

    def _write(self, data: bytes) -> None:
        master = self._master
        if master is None:
            return
        try:
            view = memoryview(data)
            while view:
                n = os.write(master, view)
                view = view[n:]
        except OSError as exc:
            self.errors.append(f"pty write failed: {exc}")

    def _take(self, kind: str, rate: float, rpc: int) -> bool:
        with self._lock:
            for key in ((kind, rpc), (kind, None)):
                if self._forced[key] > 0:
                    self._forced[key] -= 1
                    return True
        return rate > 0 and bool(self._rng.random() < rate)

    def _garbage(self) -> bytes:
        n = int(self._rng.integers(1, self.faults["garbage_len"] + 1))
        return self._rng.integers(0, 256, size=n, dtype=np.uint8).tobytes()

    def _sleep(self, sim_s: float) -> None:
        wall = sim_s / self.time_scale
        if wall > 0:
            self._stop.wait(wall)

    def _handle(self, line: bytes) -> None:
        try:
            req = gc.parse_request(line)
        except gc.GeoComChecksumError:
            self.stats["bad_request_crc"] += 1
            m = _TRID_RE.match(line)
            trid = int(m.group(1)) if m else 0
            self._write(gc.format_reply(gc.Grc.COM_SRVR_RX_CHECKSUM_ERROR, trid, 0, use_crc=True))
            return
        except gc.GeoComParseError:
            self.stats["bad_request"] += 1
            self._write(gc.format_reply(gc.Grc.COM_CANT_DECODE_REQ, 0, 0))
            return
        self.stats["requests"] += 1
        f = self.faults
        if self._take("vanish", 0.0, req.rpc) or (
            f["vanish_after"] is not None and self.stats["requests"] >= f["vanish_after"]
        ):
            self._do_vanish()
            return
        if self._take("drop", f["drop_rate"], req.rpc):
            self.stats["drop"] += 1
            return
        trid = req.trid if req.trid is not None else 0
        com_rc, rc, values = self._dispatch(req)
        reply = gc.format_reply(
            com_rc, trid, rc, values, use_crc=req.crc is not None, precision=self.precision
        )
        if self._take("slow", f["slow_rate"], req.rpc):
            self.stats["slow"] += 1
            self._sleep(f["slow_delay_s"])
            if self._stop.is_set():
                return
        mode = None
        if self._take("garbage_before", 0.0, req.rpc):
            mode = "before"
        elif self._take("garbage_instead", 0.0, req.rpc):
            mode = "instead"
        elif self._take("garbage", f["garbage_rate"], req.rpc):
            mode = f["garbage_mode"]
            if mode == "mixed":
                mode = "before" if self._rng.random() < 0.5 else "instead"
        if mode == "before":
            self.stats["garbage"] += 1
            self._write(self._garbage() + reply)
        elif mode == "instead":
            self.stats["garbage"] += 1
            junk = self._garbage()
            self._write(junk + (gc.TERMINATOR if self._rng.random() < 0.5 else b""))
        else:
            self._write(reply)
        self.stats["replies"] += 1

    # ------------------------------------------------------------------ the instrument
    def _instrument_ms(self) -> int:
        """Instrument clock in ms of simulated time since start (wraps like a 32-bit long)."""
        scale = self.time_scale if math.isfinite(self.time_scale) else 1.0
        return int((time.monotonic() - self._t0) * 1000 * scale) % 2**31

    def _dispatch(self, req: gc.Request) -> tuple[int, int, tuple]:
        rpc = req.rpc
        try:
            if rpc == gc.Rpc.COM_NullProc:
                return 0, gc.Grc.OK, ()
            if rpc == gc.Rpc.COM_GetDoublePrecision:
                return 0, gc.Grc.OK, (self.precision,)
            if rpc == gc.Rpc.COM_SetDoublePrecision:
                (digits,) = (gc.decode_long(p) for p in req.params)
                if not 0 <= digits <= 15:
                    return 0, gc.Grc.IVPARAM, ()
                self.precision = digits
                return 0, gc.Grc.OK, ()
            if rpc == gc.Rpc.COM_GetSWVersion:
                return 0, gc.Grc.OK, self.geocom_version
            if rpc == gc.Rpc.CSV_GetInstrumentNo:
                return 0, gc.Grc.OK, (self.serial_number,)
            if rpc == gc.Rpc.CSV_GetInstrumentName:
                return 0, gc.Grc.OK, (self.instrument_name,)
            if rpc == gc.Rpc.CSV_GetSWVersion:
                return 0, gc.Grc.OK, self.firmware_version
            if rpc == gc.Rpc.TMC_GetStation:  # the station at the tracker frame's origin
                return 0, gc.Grc.OK, (0.0, 0.0, 0.0, 0.0)
            if rpc in (gc.Rpc.TMC_GetPrismCorr, gc.Rpc.TMC_GetAtmPpm):
                return 0, gc.Grc.OK, (0.0,)  # the world's SMR and air: no correction applied
            if rpc in (gc.Rpc.AUS_SetUserAtrState, gc.Rpc.AUS_SetUserLockState):
                (on,) = (gc.decode_long(p) for p in req.params)
                if rpc == gc.Rpc.AUS_SetUserLockState:
                    self._lock_mode = bool(on)
                    self._locked = self._locked and self._lock_mode
                return 0, gc.Grc.OK, ()
            if rpc == gc.Rpc.AUT_FineAdjust:
                if self._take("lock_lost", 0.0, req.rpc):  # the SMR is not in the window
                    self.stats["lock_lost"] += 1
                    return 0, AUT_NO_TARGET, ()
                self._fine_adjusted = True
                return 0, gc.Grc.OK, ()
            if rpc == gc.Rpc.AUT_LockIn:
                if not (self._lock_mode and self._fine_adjusted):
                    return 0, gc.Grc.FATAL, ()
                self._locked = True
                return 0, gc.Grc.OK, ()
            if rpc == gc.Rpc.MOT_ReadLockStatus:
                if self._locked and self._take("lock_lost", 0.0, req.rpc):
                    self.stats["lock_lost"] += 1
                    self._locked = self._fine_adjusted = False
                return 0, gc.Grc.OK, (int(self._locked),)
            if rpc == gc.Rpc.TMC_DoMeasure:
                return self._do_measure(req)
            if rpc == gc.Rpc.TMC_GetCoordinate:
                return self._get_coordinate(req)
        except (gc.GeoComParseError, ValueError):
            return 0, gc.Grc.IVPARAM, ()
        return gc.Grc.COM_PROC_UNAVAIL, 0, ()

    def _do_measure(self, req: gc.Request) -> tuple[int, int, tuple]:
        if len(req.params) != 2:
            return 0, gc.Grc.IVPARAM, ()
        prg, _incline = (gc.decode_long(p) for p in req.params)
        if prg in _CLEAR_PRGS:
            self._stored = None
            return 0, gc.Grc.OK, ()
        if prg not in _MEASURE_PRGS:
            return 0, gc.Grc.OK, ()  # signal / frequency programs: nothing to store
        self._sleep(self.measure_time_s)
        if self._stored is not None and self._take("stale", self.faults["stale_rate"], req.rpc):
            self.stats["stale"] += 1
            return 0, gc.Grc.OK, ()  # nothing measured: the stored coordinate stays
        try:
            p, status = self.measure_fn()
            p = np.asarray(p, dtype=float)
            if p.shape != (3,):
                raise ValueError(f"measure_fn returned position of shape {p.shape}, not (3,)")
        except Exception as exc:  # noqa: BLE001 - the world failing must not kill the server
            self.errors.append(f"measure_fn failed: {exc!r}")
            self._stored = None
            return 0, gc.Grc.FATAL, ()
        if status == "ok" and not np.all(np.isfinite(p)):
            status = "beam_broken"
        if self._take("beam_break", self.faults["beam_break_rate"], req.rpc):
            self.stats["beam_break"] += 1
            status = "beam_broken"
        t_ms = self._instrument_ms()
        if self._last_coord_ms is not None:  # not in or behind the last one's millisecond
            step = (t_ms - self._last_coord_ms) % 2**31
            if step == 0 or step > 2**30:
                t_ms = (self._last_coord_ms + 1) % 2**31
        self._last_coord_ms = t_ms
        self._stored = (p, str(status), t_ms)
        return 0, gc.Grc.OK, ()

    def _get_coordinate(self, req: gc.Request) -> tuple[int, int, tuple]:
        if len(req.params) != 2:
            return 0, gc.Grc.IVPARAM, ()
        _wait_ms, _incline = (gc.decode_long(p) for p in req.params)
        zeros = (0.0, 0.0, 0.0, 0, 0.0, 0.0, 0.0, 0)
        if self._stored is None:
            return 0, gc.Grc.TMC_ANGLE_OK, zeros
        p, status, t_ms = self._stored
        rc = _STATUS_RC.get(status, gc.Grc.TMC_ANGLE_ERROR)
        if rc != gc.Grc.OK:
            return 0, rc, zeros
        e, n, h = gc.enh_from_p_tracker(p)
        return 0, gc.Grc.OK, (e, n, h, t_ms, e, n, h, t_ms)
