"""`Tracker` over RS-232 speaking GeoCOM (Leica), with pyserial.

One measurement = `TMC_DoMeasure(TMC_DEF_DIST, TMC_AUTO_INC)` then
`TMC_GetCoordinate(wait_ms, TMC_AUTO_INC)`; the coordinate (E, N, H) is the SMR position in the
`tracker` frame (see `workcell.drivers.geocom.p_tracker_from_enh`).

Status of a reading (from the TMC return code of either call):
- `ok`: GRC_OK, and the "results valid with a warning" codes TMC_NO_FULL_CORRECTION (1283) and
  TMC_ACCURACY_GUARANTEE (1284) (the warning is kept in `extra["warning"]`);
- `beam_broken`: "angles ok, no distance" TMC_ANGLE_OK (1285), TMC_ANGLE_NOT_FULL_CORR (1288),
  TMC_ANGLE_NO_ACC_GUARANTY (1289), and TMC_DIST_ERROR (1292, no target found); position and
  sigma are nan;
- `error`: any other non-zero procedure code (angle error, busy, ...); position and sigma nan.
  Also a coordinate that no laser tracker measures: non-finite, or farther than
  `TRACKER_RANGE_M` (200 m, the bound the recording checks use) from the instrument
  (`extra["message"]` says which, and a `bad_reading` fault is logged).
Procedure codes are instrument answers, so `measure()` returns them as a reading; it raises only
for the link: `DeviceError` when no valid reply came after the retries, `DeviceUnreachable` when
the port cannot be opened or vanished.

sigma_m: the stated accuracy of a laser tracker is an MPE, U = +-(a + b * range) with
a = 15 um, b = 6 um/m (Leica AT960 class). Typical errors are half the MPE; we take that half as a
2-sigma bound, so per axis sigma = (a + b * range) / 4 -- the same model the simulated world
(`sim_devices.truth.TrackerNoise`) uses. Change with `mpe_a_m`, `mpe_b_m_per_m`, `sigma_divisor`.

Link robustness: every request carries a fresh transaction id (1..32767) and only a reply with the
same id is accepted (late replies to earlier requests are skipped and logged as `stale_reply`).
A malformed line, a CRC mismatch, a transient COM error code or a time-out triggers a resync --
flush the input, send a bare LF (clears the instrument's receive buffer), then COM_NullProc until
one clean reply with a matching id -- and the request is sent again, up to `retries` times.
If a time-out is followed by a failed resync (not even COM_NullProc answers), `DeviceError` is
raised at once instead of re-sending: "is silent" when no byte came back, "answers, but not with
GeoCOM replies to our requests" when something did (replies carrying another transaction id,
lines that are not GeoCOM, bytes without a line end). A non-transient COM code (e.g.
COM_PROC_UNAVAIL, COM_SRVR_IS_SLEEPING) raises `DeviceError` with its name. Worst cases with the
defaults (timeout_s=2, retries=2): a silent instrument costs 4 x 2 s = 8 s per call; a port that
vanished fails at the next read/write, immediately, with `DeviceUnreachable`; after that
`measure()` keeps raising `DeviceUnreachable` until `reconnect()` succeeds.

Everything handled is appended to `fault_log` as `(kind, message)`; drain it with `pop_faults()`.
Kinds: `timeout`, `garbage`, `checksum`, `stale_reply`, `com_error`, `resync`, `resync_failed`,
`gave_up`, `port_vanished`, `bad_reading`. `fault_counts` keeps running totals per kind (never drained).
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np
import serial

from workcell.drivers import geocom as gc
from workcell.drivers.protocols import (
    TRACKER_RANGE_M,
    DeviceError,
    DeviceUnreachable,
    OtherInstrument,
    TrackerReading,
)

try:  # pyserial's POSIX backend lets termios.error (not an OSError) escape from flush()
    import termios

    _IO_ERRORS: tuple[type[BaseException], ...] = (
        serial.SerialException,
        OSError,
        termios.error,
    )
except ImportError:  # pragma: no cover - Windows
    _IO_ERRORS = (serial.SerialException, OSError)

BEAM_BROKEN_CODES: frozenset[int] = gc.ANGLE_ONLY_CODES | {gc.Grc.TMC_DIST_ERROR}


LOCK_SEARCH_RAD = 0.02  # AUT_FineAdjust's search window (width and height) to find the SMR


class _Timeout(Exception):
    pass


class NotGeoComReplies(DeviceError):
    """Bytes come back from the port, but no GeoCOM reply to our request among them."""


class SerialTracker:
    """GeoCOM tracker on a serial port (`/dev/ttyUSB0`, `/dev/pts/N`, `loop://`, `rfc2217://`).

    timeout_s: time allowed for one reply (TMC_GetCoordinate gets `measure_wait_s` on top).
    retries: how many times a request is re-sent after a time-out or a garbled reply; so a dead
    link costs about (retries + 1) * timeout_s plus the resync attempts before `DeviceError`.
    """

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115200,
        timeout_s: float = 2.0,
        retries: int = 2,
        use_crc: bool = False,
        measure_wait_s: float = 1.0,
        mpe_a_m: float = 15e-6,
        mpe_b_m_per_m: float = 6e-6,
        sigma_divisor: float = 4.0,
        min_precision: int = 9,
        serial_factory: Callable[..., Any] = serial.serial_for_url,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        if retries < 0:
            raise ValueError(f"retries must be >= 0, got {retries!r}")
        if measure_wait_s < 0:
            raise ValueError(f"measure_wait_s must be >= 0, got {measure_wait_s!r}")
        if sigma_divisor <= 0:
            raise ValueError(f"sigma_divisor must be > 0, got {sigma_divisor!r}")
        self.port = port
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.use_crc = bool(use_crc)
        self.measure_wait_s = float(measure_wait_s)
        self.mpe_a_m = float(mpe_a_m)
        self.mpe_b_m_per_m = float(mpe_b_m_per_m)
        self.sigma_divisor = float(sigma_divisor)
        self.min_precision = int(min_precision)
        self._serial_factory = serial_factory
        self._clock = clock
        self._wall_clock = wall_clock
        self._poll_s = min(0.05, self.timeout_s)
        self._ser: Any = None
        self._buf = bytearray()
        self._trid = 0
        self._lock = threading.RLock()
        self.instrument_name: str | None = None
        self.serial_number: int | None = None  # CSV_GetInstrumentNo, read on connect
        self.setup: dict = {}  # station, prism constant, ppm as the instrument answers them
        self.lock = ""  # the target lock at connect: "locked", or why not
        self.lock_mode = False  # ATR/LOCK on: each measurement checks the lock first
        self.precision: int = 15
        self.fault_log: list[tuple[str, str]] = []
        self.fault_counts: Counter[str] = Counter()
        # what came back that was not the awaited reply (told apart from silence in errors)
        self._rx = Counter()  # bytes, stale (other transaction id), junk lines, unterminated
        self._rx_tail = b""
        self._lost = False  # the port vanished under us; cleared by a successful connect()
        # (CoordTime ms, E, N, H) of the last coordinate read: a reply carrying the same time and
        # the very same coordinates is that measurement again, not a new one (a new one differs
        # by its noise; an instrument that keeps no CoordTime still gives new coordinates). Kept
        # across reconnects: `reconnect` checks that the same instrument answers.
        self._last_coord: tuple[int, float, float, float] | None = None

    # ------------------------------------------------------------------ Tracker protocol
    def connect(self) -> None:
        """Open the port, check the instrument answers COM_NullProc, read its name/precision."""
        with self._lock:
            self.close()
            try:
                self._ser = self._serial_factory(
                    self.port, baudrate=self.baudrate, timeout=self._poll_s, write_timeout=None
                )
            except (*_IO_ERRORS, ValueError) as exc:
                self._ser = None
                raise DeviceUnreachable(
                    f"tracker port {self.port!r} cannot be opened ({exc}); check the cable / USB "
                    f"adapter, the port name, and that no other program holds the port"
                ) from exc
            self._buf.clear()
            try:
                self._write(b"\n")  # a leading LF clears the instrument's receive buffer
                rx0 = self._rx.copy()
                try:
                    self._call(gc.Rpc.COM_NullProc)
                except DeviceUnreachable:
                    raise
                except NotGeoComReplies as exc:
                    raise DeviceUnreachable(f"no GeoCOM answer: {exc}") from exc
                except DeviceError as exc:
                    if self._rx["bytes"] > rx0["bytes"]:
                        hint = (
                            f"something answers on the port, but not GeoCOM: check this is the "
                            f"tracker's port, that the instrument is in GeoCOM/online mode and "
                            f"its RS-232 settings (baud rate, 8N1, CR/LF terminator); "
                            f"received {self._rx_summary(rx0)}"
                        )
                    else:
                        hint = (
                            "check the instrument is on, in GeoCOM/online mode, and its RS-232 "
                            "settings (baud rate, 8N1, CR/LF terminator)"
                        )
                    raise DeviceUnreachable(
                        f"no GeoCOM answer from the tracker on {self.port!r} at {self.baudrate} "
                        f"baud ({exc}); {hint}"
                    ) from exc
                prec = self._call_value(gc.Rpc.COM_GetDoublePrecision, gc.decode_long)
                if prec < self.min_precision:
                    # a low precision would round coordinates (4 digits = 0.1 mm)
                    rep = self._call(gc.Rpc.COM_SetDoublePrecision, (15,))
                    if rep.rc != gc.Grc.OK:
                        raise DeviceError(
                            f"tracker on {self.port!r}: double precision is {prec} digits and "
                            f"COM_SetDoublePrecision failed: {rep.describe()}"
                        )
                    prec = 15
                self.precision = min(int(prec), 15)  # GeoCOM allows 0..15 digits
                self.instrument_name = self._call_value(
                    gc.Rpc.CSV_GetInstrumentName, gc.decode_string
                )
                self.serial_number = self._serial_number()
                self.setup = self._instrument_setup()
                self.lock = self._lock_on()
                self._lost = False
            except BaseException:
                self.close()
                raise

    def _serial_number(self) -> int | None:
        """CSV_GetInstrumentNo; None from an instrument that does not answer it."""
        try:
            rep = self._call(gc.Rpc.CSV_GetInstrumentNo)
            if rep.rc != gc.Grc.OK:
                return None
            return int(gc.decode_single(rep, gc.decode_long))
        except DeviceUnreachable:
            raise
        except (DeviceError, ValueError):
            return None

    def _optional(self, rpc: int, params: tuple = (), n: int = 0) -> tuple[float, ...] | None:
        """`n` doubles an RPC returns (none for n = 0), or None when the instrument does not
        answer it (an RPC it has not, a procedure code): the setup and lock queries are not
        every GeoCOM instrument's, and their refusals are not faults of the link."""
        before = len(self.fault_log)
        try:
            rep = self._call(rpc, params)
            if rep.rc != gc.Grc.OK or len(rep.values) < n:
                return None
            return tuple(gc.decode_double(v) for v in rep.values[:n])
        except DeviceUnreachable:
            raise
        except (DeviceError, ValueError):
            for kind, _ in self.fault_log[before:]:
                self.fault_counts[kind] -= 1
            del self.fault_log[before:]
            return None

    def _instrument_setup(self) -> dict:
        """What the instrument applies to its coordinates, as it answers: its station (E0, N0,
        H0 and instrument height: the `tracker` frame's origin), the prism constant (an offset
        along every line of sight) and the atmospheric correction (a scale). Recorded in the
        session: the station is absorbed by the fitted tracker_T_base, the prism constant and
        the ppm are not, so a resume refuses an instrument whose setup changed."""
        setup: dict = {}
        if (st := self._optional(gc.Rpc.TMC_GetStation, n=4)) is not None:
            setup["station_enh_m"] = list(st[:3])
            setup["instrument_height_m"] = st[3]
        if (pc := self._optional(gc.Rpc.TMC_GetPrismCorr, n=1)) is not None:
            setup["prism_constant_m"] = pc[0]
        if (ppm := self._optional(gc.Rpc.TMC_GetAtmPpm, n=1)) is not None:
            setup["atm_ppm"] = ppm[0]
        return setup

    def _lock_on(self) -> str:
        """ATR and LOCK modes on, then lock onto the target (AUS_SetUserAtrState,
        AUS_SetUserLockState, AUT_LockIn), so that the instrument follows the SMR as the arm
        moves it (a GeoCOM instrument measures where it points: without a lock every pose after
        a move is a beam break). "locked", or why not; an instrument without ATR (NOT_IMPL)
        measures where it points, as before, and `measure` then does not check the lock."""
        self.lock_mode = False
        for rpc in (gc.Rpc.AUS_SetUserAtrState, gc.Rpc.AUS_SetUserLockState):
            if self._optional(rpc, (1,)) is None:
                return f"no target lock: the instrument refuses {gc.rpc_name(rpc)} (no ATR?)"
        self.lock_mode = True
        if not self._lock_in():
            return "lock mode on, not locked onto the target yet (the first measurement tries)"
        return "locked"

    def _lock_in(self) -> bool:
        """Find the target in a small window and lock onto it (AUT_FineAdjust, AUT_LockIn)."""
        if self._optional(gc.Rpc.AUT_FineAdjust, (LOCK_SEARCH_RAD, LOCK_SEARCH_RAD, 0)) is None:
            return False
        return self._optional(gc.Rpc.AUT_LockIn) is not None

    def _locked(self) -> bool:
        """MOT_ReadLockStatus says the instrument follows the target; else one try to lock in
        again (the beam was broken: a cable, an arm link between)."""
        rep = self._call(gc.Rpc.MOT_ReadLockStatus)
        try:
            locked = rep.rc == gc.Grc.OK and gc.decode_single(rep, gc.decode_long) == (
                gc.MOT_LOCKED_IN
            )
        except ValueError:
            locked = False
        return locked or self._lock_in()

    def reconnect(self) -> None:
        """Close and connect again (after `DeviceUnreachable`, e.g. a USB adapter re-plugged).
        The instrument that answers must be the one connected before: another serial number
        (another tracker on the port name: its station, and so its frame, is not the
        campaign's) raises `OtherInstrument` and leaves the port closed."""
        before = (self.instrument_name, self.serial_number)
        self.connect()
        after = (self.instrument_name, self.serial_number)
        if before[1] is not None and after[1] != before[1]:
            self.close()
            now = "gives no serial number" if after[1] is None else f"is serial number {after[1]}"
            raise OtherInstrument(
                f"tracker on {self.port!r}: the instrument that answers after reconnecting "
                f"{now} ({after[0]}), not serial number {before[1]} ({before[0]}) this "
                "session measured with: its frame is not this session's; connect that tracker "
                "again"
            )

    def close(self) -> None:
        with self._lock:
            ser, self._ser = self._ser, None
            if ser is not None:
                try:
                    ser.close()
                except Exception:  # noqa: BLE001 - closing a vanished port may fail; ignore
                    pass

    @property
    def is_connected(self) -> bool:
        return self._ser is not None

    def measure(self) -> TrackerReading:
        """TMC_DoMeasure + TMC_GetCoordinate -> one reading (status ok/beam_broken/error)."""
        with self._lock:
            faults_before = len(self.fault_log)
            if self.lock_mode and not self._locked():
                return self._no_position(
                    "beam_broken",
                    {
                        "rc": int(gc.Grc.OK),
                        "rc_name": "not_locked",
                        "message": "the instrument is not locked onto the target and could "
                        "not lock in again (the beam broken, the SMR out of the search window)",
                        "faults": len(self.fault_log) - faults_before,
                    },
                )
            rep = self._call(
                gc.Rpc.TMC_DoMeasure,
                (int(gc.TmcMeasurePrg.TMC_DEF_DIST), int(gc.TmcInclinePrg.TMC_AUTO_INC)),
            )
            if rep.rc != gc.Grc.OK:
                return self._reading_without_coordinate(rep.rc, "TMC_DoMeasure", faults_before)
            wait_ms = int(round(self.measure_wait_s * 1000))
            rep = self._call(
                gc.Rpc.TMC_GetCoordinate,
                (wait_ms, int(gc.TmcInclinePrg.TMC_AUTO_INC)),
                extra_timeout_s=self.measure_wait_s,
                decode=_decode_coordinate_if_valid,
            )
            t_s = self._wall_clock()
            if rep.rc != gc.Grc.OK and rep.rc not in gc.COORDINATE_WARNING_CODES:
                return self._reading_without_coordinate(rep.rc, "TMC_GetCoordinate", faults_before)
            coord = gc.decode_coordinate(rep, finite=False)
            p = gc.p_tracker_from_enh(coord.e_m, coord.n_m, coord.h_m)
            bad = _implausible(p)
            this = (coord.time_ms, coord.e_m, coord.n_m, coord.h_m)
            if bad is None and this == self._last_coord:
                bad = (
                    f"TMC_GetCoordinate returned the previous measurement again (CoordTime "
                    f"{coord.time_ms} ms and coordinates unchanged): the instrument measured nothing new"
                )
                kind = "stale_reading"
            else:
                kind = "bad_reading"
                if bad is None:
                    self._last_coord = this
            if bad is not None:
                self._fault(kind, f"tracker on {self.port!r}: {bad}; reading refused")
                return self._no_position(
                    "error",
                    {
                        "rc": int(rep.rc),
                        "rc_name": kind,
                        "instrument_time_ms": coord.time_ms,
                        "message": f"TMC_GetCoordinate: {bad}",
                        "faults": len(self.fault_log) - faults_before,
                    },
                    t_s,
                )
            extra: dict[str, Any] = {
                "rc": int(rep.rc),
                "rc_name": gc.return_code_name(rep.rc),
                "instrument_time_ms": coord.time_ms,
                "faults": len(self.fault_log) - faults_before,
            }
            if rep.rc != gc.Grc.OK:
                extra["warning"] = gc.describe_return_code(rep.rc)
            return TrackerReading(
                position_m=p, sigma_m=self.sigma_for(p), status="ok", t_s=t_s, extra=extra
            )

    # ------------------------------------------------------------------ public helpers
    def sigma_for(self, p_tracker: np.ndarray) -> np.ndarray:
        """Per-axis 1-sigma (m) of a reading at `p_tracker`: (a + b * range) / sigma_divisor."""
        r = float(np.linalg.norm(np.asarray(p_tracker, dtype=float)))
        s = (self.mpe_a_m + self.mpe_b_m_per_m * r) / self.sigma_divisor
        return np.full(3, s)

    def pop_faults(self) -> list[tuple[str, str]]:
        """Return and clear the faults handled since the last call, oldest first."""
        with self._lock:
            out, self.fault_log = self.fault_log, []
            return out

    def call(
        self, rpc: int, params: tuple | list = (), *, extra_timeout_s: float = 0.0
    ) -> gc.Reply:
        """Any GeoCOM RPC with the same retry/resync policy (reply's procedure code unchecked)."""
        with self._lock:
            return self._call(rpc, tuple(params), extra_timeout_s=extra_timeout_s)

    def __enter__(self) -> SerialTracker:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ internals
    def _call_value(self, rpc: int, decoder: Callable[[str], Any]) -> Any:
        """Call an RPC that returns one value; a non-zero procedure code -> DeviceError."""

        def check(rep: gc.Reply) -> None:
            if rep.com_rc == 0 and rep.rc == gc.Grc.OK:
                gc.decode_single(rep, decoder)

        rep = self._call(rpc, decode=check)
        if rep.rc != gc.Grc.OK:
            raise DeviceError(
                f"tracker on {self.port!r}: {gc.rpc_name(rpc)} failed: {rep.describe()}"
            )
        return gc.decode_single(rep, decoder)

    def _reading_without_coordinate(
        self, rc: int, where: str, faults_before: int
    ) -> TrackerReading:
        return self._no_position(
            "beam_broken" if rc in BEAM_BROKEN_CODES else "error",
            {
                "rc": int(rc),
                "rc_name": gc.return_code_name(rc),
                "message": f"{where}: {gc.describe_return_code(rc)}",
                "faults": len(self.fault_log) - faults_before,
            },
        )

    def _no_position(self, status: str, extra: dict, t_s: float | None = None) -> TrackerReading:
        """A reading without a position (status beam_broken or error): position and sigma nan."""
        nan3 = np.full(3, np.nan)
        return TrackerReading(
            position_m=nan3,
            sigma_m=nan3.copy(),
            status=status,
            t_s=self._wall_clock() if t_s is None else t_s,
            extra=extra,
        )

    def _rx_summary(self, rx0: Counter) -> str:
        """What came back since `rx0` that was not the awaited reply, for an error message."""
        d = self._rx - rx0
        parts = []
        if d["stale"]:
            parts.append(
                f"{d['stale']} GeoCOM replies carrying another transaction id (late replies, "
                "or replies to another program's requests)"
            )
        if d["junk"]:
            parts.append(f"{d['junk']} lines that are not GeoCOM replies")
        loose = d["unterminated"] + len(self._buf)
        if loose:
            parts.append(f"{loose} bytes without a line end (LF)")
        parts.append(f"{d['bytes']} bytes in all, the last {self._rx_tail[-40:]!r}")
        return ", ".join(parts)

    def _fault(self, kind: str, message: str) -> None:
        self.fault_log.append((kind, message))
        self.fault_counts[kind] += 1

    def _next_trid(self) -> int:
        self._trid = self._trid % gc.MAX_TRANSACTION_ID + 1
        return self._trid

    def _vanished(self, during: str, exc: BaseException) -> DeviceUnreachable:
        where = self.port
        gone = ""
        if where.startswith("/") and not os.path.exists(where):
            gone = f" (the device node {where} no longer exists)"
        msg = (
            f"tracker serial port {where!r} vanished during {during}{gone}: {exc}; check the "
            f"cable / USB adapter and power, then reconnect"
        )
        self._fault("port_vanished", msg)
        self.close()
        self._lost = True
        return DeviceUnreachable(msg)

    def _require_open(self) -> Any:
        if self._ser is None:
            if self._lost:
                raise DeviceUnreachable(
                    f"tracker on {self.port!r}: the port was lost earlier and is not back; check the "
                    "cable / USB adapter and power"
                )
            raise DeviceError(f"tracker on {self.port!r} is not connected")
        return self._ser

    def _write(self, data: bytes) -> None:
        ser = self._require_open()
        try:
            ser.write(data)
            ser.flush()
        except _IO_ERRORS as exc:
            raise self._vanished("write", exc) from exc

    def _flush_input(self) -> None:
        ser = self._require_open()
        self._rx["unterminated"] += len(self._buf)  # bytes that never became a line
        self._buf.clear()
        try:
            ser.reset_input_buffer()
        except _IO_ERRORS as exc:
            raise self._vanished("input flush", exc) from exc

    def _read_line(self, deadline: float) -> bytes:
        """Next LF-terminated line (CR LF stripped); `_Timeout` at the deadline."""
        ser = self._require_open()
        while True:
            i = self._buf.find(b"\n")
            if i >= 0:
                line = bytes(self._buf[:i])
                del self._buf[: i + 1]
                return line[:-1] if line.endswith(b"\r") else line
            if len(self._buf) > gc.MAX_LINE_BYTES:
                junk = bytes(self._buf[:60])
                self._rx["unterminated"] += len(self._buf)
                self._buf.clear()
                raise gc.GeoComParseError(f"over {gc.MAX_LINE_BYTES} bytes without LF: {junk!r}")
            if self._clock() >= deadline:
                raise _Timeout()
            try:
                n = ser.in_waiting
                chunk = ser.read(n if n > 0 else 1)
            except _IO_ERRORS as exc:
                raise self._vanished("read", exc) from exc
            if chunk:
                self._buf.extend(chunk)
                self._rx["bytes"] += len(chunk)
                self._rx_tail = (self._rx_tail + chunk)[-40:]

    def _read_reply(self, trid: int, deadline: float, *, skip_garbage: bool) -> gc.Reply:
        """The reply carrying `trid`; skips stale replies (and garbage if `skip_garbage`)."""
        while True:
            try:
                # a flood without line end is garbage like any unparsable line (it escaped the
                # resync's and the campaign's retries as a ValueError until 2026-11-28)
                line = self._read_line(deadline)
                if not line.strip():
                    continue
                rep = gc.parse_reply(line, expect_crc=self.use_crc)
            except gc.GeoComParseError:
                self._rx["junk"] += 1
                if not skip_garbage:
                    raise
                if self._clock() >= deadline:
                    raise _Timeout() from None
                continue
            if rep.trid != trid:
                self._rx["stale"] += 1
                self._fault(
                    "stale_reply",
                    f"skipped a reply with transaction id {rep.trid} while waiting for {trid}",
                )
                if self._clock() >= deadline:
                    raise _Timeout()
                continue
            return rep

    def _resync(self, reason: str) -> gc.Reply | None:
        """Flush, LF, then COM_NullProc until one clean reply with a matching id (returned;
        None when none came)."""
        self._flush_input()
        self._write(b"\n")
        for _attempt in range(self.retries + 1):
            trid = self._next_trid()
            self._write(gc.format_request(gc.Rpc.COM_NullProc, trid=trid, use_crc=self.use_crc))
            try:
                rep = self._read_reply(trid, self._clock() + self.timeout_s, skip_garbage=True)
            except _Timeout:
                continue
            if rep.com_rc == 0:
                self._fault("resync", f"link resynchronised after {reason}")
                return rep
        self._fault("resync_failed", f"no clean COM_NullProc reply after {reason}")
        return None

    def _resync_answering(self, rpc: int, reason: str) -> gc.Reply | None:
        """`_resync`; its clean COM_NullProc reply when the call being retried is COM_NullProc
        itself (the resync made the very call: that is its answer), else None."""
        clean = self._resync(reason)
        return clean if rpc == gc.Rpc.COM_NullProc else None

    def _call(
        self,
        rpc: int,
        params: tuple = (),
        *,
        extra_timeout_s: float = 0.0,
        decode: Callable[[gc.Reply], object] | None = None,
    ) -> gc.Reply:
        name = gc.rpc_name(rpc)
        last = "no attempt"
        rx0 = self._rx.copy()
        for attempt in range(self.retries + 1):
            trid = self._next_trid()
            req = gc.format_request(
                rpc, params, trid=trid, use_crc=self.use_crc, precision=self.precision
            )
            self._write(req)
            deadline = self._clock() + self.timeout_s + extra_timeout_s
            try:
                rep = self._read_reply(trid, deadline, skip_garbage=False)
                if decode is not None:
                    decode(rep)
            except _Timeout:
                last = f"no reply within {self.timeout_s + extra_timeout_s:.3g} s"
                self._fault("timeout", f"{name} (attempt {attempt + 1}): {last}")
                clean = self._resync(f"a time-out on {name}")
                if clean is not None and rpc == gc.Rpc.COM_NullProc:
                    return clean  # the resync made the very call: a clean answer is one
                if clean is None:
                    # not even COM_NullProc answers: re-sending the request is pointless
                    waited = (
                        f"no reply to {name} within {self.timeout_s + extra_timeout_s:.3g} s "
                        f"and none to {self.retries + 1} COM_NullProc tries"
                    )
                    if self._rx["bytes"] > rx0["bytes"]:
                        msg = (
                            f"tracker on {self.port!r} answers, but not with GeoCOM replies to "
                            f"our requests ({waited}; received {self._rx_summary(rx0)}): check "
                            f"this is the tracker's port, that the instrument is in GeoCOM "
                            f"(online) mode with a CR/LF terminator, and that no other program "
                            f"talks on the port"
                        )
                        self._fault("gave_up", msg)
                        raise NotGeoComReplies(msg) from None
                    msg = (
                        f"tracker on {self.port!r} is silent: {waited}; check the instrument "
                        f"is on and awake, and the cable"
                    )
                    self._fault("gave_up", msg)
                    raise DeviceError(msg) from None
                continue
            except gc.GeoComChecksumError as exc:
                last = f"bad checksum: {exc}"
                self._fault("checksum", f"{name} (attempt {attempt + 1}): {exc}")
                if (
                    answer := self._resync_answering(rpc, f"a checksum error on {name}")
                ) is not None:
                    return answer
                continue
            except gc.GeoComParseError as exc:
                last = f"garbled reply: {exc}"
                self._fault("garbage", f"{name} (attempt {attempt + 1}): {exc}")
                if (
                    answer := self._resync_answering(rpc, f"a garbled reply to {name}")
                ) is not None:
                    return answer
                continue
            if rep.com_rc != 0:
                last = "COM " + gc.describe_return_code(rep.com_rc)
                self._fault("com_error", f"{name} (attempt {attempt + 1}): {last}")
                if rep.com_rc in gc.COM_TRANSIENT_CODES:
                    if (
                        answer := self._resync_answering(rpc, f"a COM error on {name}")
                    ) is not None:
                        return answer
                    continue
                raise DeviceError(f"tracker on {self.port!r}: {name} failed: {last}")
            return rep
        msg = (
            f"tracker on {self.port!r}: no valid reply to {name} after {self.retries + 1} "
            f"attempts (timeout {self.timeout_s:.3g} s each); last problem: {last}"
        )
        self._fault("gave_up", msg)
        raise DeviceError(msg)


def _decode_coordinate_if_valid(rep: gc.Reply) -> None:
    """A coordinate reply whose code says 'valid' must carry 8 decodable values (well-formed;
    whether the values are plausible is the reading's business, `_implausible`)."""
    if rep.com_rc == 0 and (rep.rc == gc.Grc.OK or rep.rc in gc.COORDINATE_WARNING_CODES):
        gc.decode_coordinate(rep, finite=False)


def _implausible(p: np.ndarray) -> str | None:
    """Why a coordinate is no laser-tracker measurement, or None."""
    if not np.all(np.isfinite(p)):
        return f"coordinate {p.tolist()} is not finite"
    dist = math.hypot(*(float(x) for x in p))  # no overflow warning at 1e300
    if dist > TRACKER_RANGE_M:
        return (
            f"coordinate {dist:.4g} m from the instrument (no laser tracker measures beyond "
            f"{TRACKER_RANGE_M:g} m; a unit or precision setting?)"
        )
    return None
