"""GeoCOM ASCII protocol (Leica total stations / trackers): pure functions, no I/O.

Wire format (GeoCOM reference manual, TPS1200/TS30/TM30 v1.50, section 2 "ASCII protocol"):

    request  [<LF>]%R1Q,<RPC>[,<TrId>][,<CRC>]:[<P0>][,<P1>,...]<CR><LF>
    reply    %R1P,<RC_COM>[,<TrId>][,<CRC>]:<RC>[,<P0>,<P1>,...]<CR><LF>

- `RC_COM` is the communication return code (0 = the request arrived and was decoded), `RC` the
  return code of the called procedure. A leading LF clears the instrument's receive buffer.
- `TrId` is echoed by the instrument; 0 in the reply if the request had none.
- CRC (optional, newer firmware): a decimal CRC-16/ARC (poly 0x8005 reflected = 0xA001, init 0,
  no final xor; check value of b"123456789" is 0xBB3D) written as a third header field after the
  transaction id. It is computed over the whole line *without* the CRC field and without the
  terminator. The TPS1200 manual does not document it; the placement follows what GeoComPy found
  on instruments (its issue #94 / PR #95). A reply without a CRC field is accepted only when no
  CRC is expected.
- Values: doubles in decimal notation (`COM_GetDoublePrecision` digits after the point), longs in
  decimal or 0x-hex, strings in double quotes with `\\ " % ~` escaped by a backslash and bytes
  outside 0x20..0x7E written as `\\xNN`, bytes as `'hh'`.

Frame mapping: `TMC_GetCoordinate` returns easting, northing, height of the target in the
instrument's own coordinate system (metres). With the station set at the origin (E0=N0=H0=0,
orientation 0, instrument height 0 -- what a tracker cell uses) that is the `tracker` frame:
``p_tracker = (E, N, H)`` in metres, see `p_tracker_from_enh`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import TypeVar

import numpy as np

T = TypeVar("T")

TERMINATOR = b"\r\n"
MAX_LINE_BYTES = 4096  # longer lines are garbage: no GeoCOM reply we use is near this
MAX_TRANSACTION_ID = 0x7FFF  # transaction ids are small positive integers; we cycle 1..0x7FFF


class GeoComParseError(ValueError):
    """A line is not a well-formed GeoCOM request/reply (or a value has the wrong type)."""


class GeoComChecksumError(GeoComParseError):
    """The line is well formed but its CRC-16 does not match its content."""


# ----------------------------------------------------------------------------- RPC numbers
class Rpc(IntEnum):
    """Remote procedure numbers used here (GeoCOM reference manual)."""

    COM_NullProc = 0
    COM_SetDoublePrecision = 107
    COM_GetDoublePrecision = 108
    COM_GetSWVersion = 110
    TMC_DoMeasure = 2008
    TMC_GetStation = 2009  # E0, N0, H0 (m), instrument height (m)
    TMC_GetPrismCorr = 2023  # prism constant (m)
    TMC_GetCoordinate = 2082
    TMC_GetAtmPpm = 2151  # atmospheric correction (ppm)
    CSV_GetInstrumentNo = 5003
    CSV_GetInstrumentName = 5004
    CSV_GetSWVersion = 5034
    MOT_ReadLockStatus = 6021  # 0 not locked, 1 locked onto the target, 2 predicting
    AUT_LockIn = 9013
    AUT_FineAdjust = 9037  # search window width, height (rad), 0
    AUS_SetUserAtrState = 18005
    AUS_SetUserLockState = 18007


MOT_LOCKED_IN = 1  # MOT_ReadLockStatus: following the target


def rpc_name(rpc: int) -> str:
    try:
        return Rpc(rpc).name
    except ValueError:
        return f"RPC_{rpc}"


class TmcMeasurePrg(IntEnum):
    """TMC_MEASURE_PRG: first parameter of TMC_DoMeasure."""

    TMC_STOP = 0
    TMC_DEF_DIST = 1
    TMC_TRK_DIST = 2
    TMC_CLEAR = 3
    TMC_SIGNAL = 4
    TMC_DO_MEASURE = 6
    TMC_RTRK_DIST = 8
    TMC_RED_TRK_DIST = 10
    TMC_FREQUENCY = 11


class TmcInclinePrg(IntEnum):
    """TMC_INCLINE_PRG: inclination correction mode."""

    TMC_MEA_INC = 0
    TMC_AUTO_INC = 1
    TMC_PLANE_INC = 2


# ----------------------------------------------------------------------------- return codes
class Grc(IntEnum):
    """GeoCOM return codes used by this package (numbers from the GeoCOM reference manual)."""

    OK = 0
    UNDEFINED = 1
    IVPARAM = 2
    IVRESULT = 3
    FATAL = 4
    NOT_IMPL = 5
    TIME_OUT = 6
    SET_INCOMPL = 7
    ABORT = 8
    NOMEMORY = 9
    NOTINIT = 10
    SHUT_DOWN = 12
    SYSBUSY = 13
    HWFAILURE = 14
    LOW_POWER = 16
    BATT_EMPTY = 18
    OUT_OF_TEMP = 21
    INSTRUMENT_TILT = 22
    COM_SETTING = 23
    SLEEP_MODE = 25
    NOTOK = 26
    NA = 27
    # TMC: theodolite measurement and calculation
    TMC_NO_FULL_CORRECTION = 1283
    TMC_ACCURACY_GUARANTEE = 1284
    TMC_ANGLE_OK = 1285
    TMC_ANGLE_NOT_FULL_CORR = 1288
    TMC_ANGLE_NO_ACC_GUARANTY = 1289
    TMC_ANGLE_ERROR = 1290
    TMC_DIST_PPM = 1291
    TMC_DIST_ERROR = 1292
    TMC_BUSY = 1293
    TMC_SIGNAL_ERROR = 1294
    # COM: communication
    COM_ERO = 3072
    COM_CANT_ENCODE = 3073
    COM_CANT_DECODE = 3074
    COM_CANT_SEND = 3075
    COM_CANT_RECV = 3076
    COM_TIMEDOUT = 3077
    COM_WRONG_FORMAT = 3078
    COM_VER_MISMATCH = 3079
    COM_CANT_DECODE_REQ = 3080
    COM_PROC_UNAVAIL = 3081
    COM_CANT_ENCODE_REP = 3082
    COM_SYSTEM_ERR = 3083
    COM_FAILED = 3085
    COM_NO_BINARY = 3086
    COM_INTR = 3087
    COM_REQUIRES_8DBITS = 3090
    COM_TR_ID_MISMATCH = 3093
    COM_NOT_GEOCOM = 3094
    COM_UNKNOWN_PORT = 3095
    COM_ERO_END = 3099
    COM_OVERRUN = 3100
    COM_SRVR_RX_CHECKSUM_ERROR = 3101
    COM_CLNT_RX_CHECKSUM_ERROR = 3102
    COM_PORT_NOT_AVAILABLE = 3103
    COM_PORT_NOT_OPEN = 3104
    COM_NO_PARTNER = 3105
    COM_ERO_NOT_STARTED = 3106
    COM_CONS_REQ = 3107
    COM_SRVR_IS_SLEEPING = 3108
    COM_SRVR_IS_OFF = 3109
    COM_NO_CHECKSUM = 3110


#: code -> meaning, in our words (the manual's tables give the same codes).
RETURN_CODE_MEANING: dict[int, str] = {
    Grc.OK: "completed successfully",
    Grc.UNDEFINED: "unknown error, result unspecified",
    Grc.IVPARAM: "invalid parameter",
    Grc.IVRESULT: "invalid result",
    Grc.FATAL: "fatal error",
    Grc.NOT_IMPL: "not implemented",
    Grc.TIME_OUT: "function timed out, result unspecified",
    Grc.SET_INCOMPL: "subsystem parameter set-up incomplete",
    Grc.ABORT: "function aborted",
    Grc.NOMEMORY: "not enough memory",
    Grc.NOTINIT: "subsystem not initialised",
    Grc.SHUT_DOWN: "subsystem is down",
    Grc.SYSBUSY: "system busy with another process",
    Grc.HWFAILURE: "hardware failure",
    Grc.LOW_POWER: "aborted: supply voltage too low",
    Grc.BATT_EMPTY: "battery empty",
    Grc.OUT_OF_TEMP: "out of temperature range",
    Grc.INSTRUMENT_TILT: "instrument tilt out of range",
    Grc.COM_SETTING: "communication settings error",
    Grc.SLEEP_MODE: "instrument went to sleep mode",
    Grc.NOTOK: "function not successfully completed",
    Grc.NA: "not available",
    Grc.TMC_NO_FULL_CORRECTION: "warning: measurement without full correction (results valid)",
    Grc.TMC_ACCURACY_GUARANTEE: "info: accuracy cannot be guaranteed (results valid)",
    Grc.TMC_ANGLE_OK: "angles valid, no distance (no target / beam interrupted)",
    Grc.TMC_ANGLE_NOT_FULL_CORR: "angles valid but not fully corrected, no distance",
    Grc.TMC_ANGLE_NO_ACC_GUARANTY: "angles valid, accuracy not guaranteed, no distance",
    Grc.TMC_ANGLE_ERROR: "no angle measurement (angle or inclination error)",
    Grc.TMC_DIST_PPM: "distance error: wrong ppm/mm setting on the EDM",
    Grc.TMC_DIST_ERROR: "distance measurement not done (no aim, target not found)",
    Grc.TMC_BUSY: "TMC busy, no measurement done",
    Grc.TMC_SIGNAL_ERROR: "no signal on the EDM",
    Grc.COM_ERO: "extended runtime operation initiated",
    Grc.COM_CANT_ENCODE: "client cannot encode arguments",
    Grc.COM_CANT_DECODE: "client cannot decode results",
    Grc.COM_CANT_SEND: "hardware error while sending",
    Grc.COM_CANT_RECV: "hardware error while receiving",
    Grc.COM_TIMEDOUT: "request timed out",
    Grc.COM_WRONG_FORMAT: "packet format error",
    Grc.COM_VER_MISMATCH: "client/server version mismatch",
    Grc.COM_CANT_DECODE_REQ: "instrument cannot decode the request",
    Grc.COM_PROC_UNAVAIL: "unknown RPC number",
    Grc.COM_CANT_ENCODE_REP: "instrument cannot encode the reply",
    Grc.COM_SYSTEM_ERR: "unspecified system error",
    Grc.COM_FAILED: "unspecified communication error",
    Grc.COM_NO_BINARY: "binary protocol not available",
    Grc.COM_INTR: "call interrupted",
    Grc.COM_REQUIRES_8DBITS: "protocol needs 8-bit characters",
    Grc.COM_TR_ID_MISMATCH: "transaction id mismatch",
    Grc.COM_NOT_GEOCOM: "protocol not recognised as GeoCOM",
    Grc.COM_UNKNOWN_PORT: "invalid port address",
    Grc.COM_ERO_END: "extended runtime operation ending",
    Grc.COM_OVERRUN: "data buffer overflow",
    Grc.COM_SRVR_RX_CHECKSUM_ERROR: "instrument received a request with a bad checksum",
    Grc.COM_CLNT_RX_CHECKSUM_ERROR: "client received a reply with a bad checksum",
    Grc.COM_PORT_NOT_AVAILABLE: "port not available",
    Grc.COM_PORT_NOT_OPEN: "port not open",
    Grc.COM_NO_PARTNER: "no instrument found",
    Grc.COM_ERO_NOT_STARTED: "extended runtime operation could not be started",
    Grc.COM_CONS_REQ: "attempt to send consecutive requests",
    Grc.COM_SRVR_IS_SLEEPING: "instrument is asleep; wait and retry",
    Grc.COM_SRVR_IS_OFF: "instrument has shut down; wait and retry",
    Grc.COM_NO_CHECKSUM: "no checksum available in the ASCII protocol",
}

#: TMC codes meaning "angles measured, distance missing": for a tracker, beam not on the SMR.
ANGLE_ONLY_CODES: frozenset[int] = frozenset(
    {Grc.TMC_ANGLE_OK, Grc.TMC_ANGLE_NOT_FULL_CORR, Grc.TMC_ANGLE_NO_ACC_GUARANTY}
)
#: TMC codes whose coordinates are valid but come with a warning/info.
COORDINATE_WARNING_CODES: frozenset[int] = frozenset(
    {Grc.TMC_NO_FULL_CORRECTION, Grc.TMC_ACCURACY_GUARANTEE}
)
#: COM codes that mean "this exchange was garbled": resync and send again.
COM_TRANSIENT_CODES: frozenset[int] = frozenset(
    {
        Grc.COM_CANT_DECODE,
        Grc.COM_CANT_RECV,
        Grc.COM_TIMEDOUT,
        Grc.COM_WRONG_FORMAT,
        Grc.COM_CANT_DECODE_REQ,
        Grc.COM_OVERRUN,
        Grc.COM_SRVR_RX_CHECKSUM_ERROR,
        Grc.COM_CLNT_RX_CHECKSUM_ERROR,
        Grc.COM_TR_ID_MISMATCH,
    }
)


def return_code_name(code: int) -> str:
    try:
        return "GRC_" + Grc(code).name
    except ValueError:
        return f"GRC_{code}"


def return_code_meaning(code: int) -> str:
    return RETURN_CODE_MEANING.get(code, "unknown return code")


def describe_return_code(code: int) -> str:
    """`'GRC_TMC_ANGLE_OK (1285): angles valid, no distance ...'`."""
    return f"{return_code_name(code)} ({code}): {return_code_meaning(code)}"


# ----------------------------------------------------------------------------- CRC-16/ARC
def _make_crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _make_crc_table()


def crc16(data: bytes | str) -> int:
    """CRC-16/ARC (a.k.a. CRC-16/IBM, LHA): reflected poly 0xA001, init 0, no xorout."""
    if isinstance(data, str):
        data = data.encode("ascii")
    crc = 0
    for b in data:
        crc = _CRC_TABLE[(crc ^ b) & 0xFF] ^ (crc >> 8)
    return crc


# ----------------------------------------------------------------------------- values
_LONG_RE = re.compile(r"[+-]?(?:0[xX][0-9a-fA-F]+|[0-9]+)")
_DOUBLE_RE = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_BYTE_RE = re.compile(r"'([0-9a-fA-F]{2})'")
_STRING_ESCAPED = '\\"%~'


def encode_long(value: int) -> str:
    return f"{int(value):d}"


def encode_double(value: float, precision: int = 15) -> str:
    """Decimal notation with `precision` digits after the point, trailing zeros trimmed."""
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"GeoCOM cannot carry a non-finite double: {value!r}")
    text = f"{x:.{max(int(precision), 0)}f}"
    if "." in text:
        text = text.rstrip("0")
        if text.endswith("."):
            text += "0"
    if text in ("-0.0", "-0"):
        text = text[1:]
    return text


def encode_string(value: str) -> str:
    out = ['"']
    for ch in value:
        code = ord(ch)
        if ch in _STRING_ESCAPED:
            out.append("\\" + ch)
        elif 0x20 <= code <= 0x7E:
            out.append(ch)
        elif code <= 0xFF:
            out.append(f"\\x{code:02X}")
        else:
            raise ValueError(f"GeoCOM strings are 8-bit; cannot encode {ch!r}")
    out.append('"')
    return "".join(out)


def decode_long(text: str) -> int:
    t = text.strip()
    if not _LONG_RE.fullmatch(t):
        raise GeoComParseError(f"expected a GeoCOM long, got {text!r}")
    return int(t, 0) if "x" in t.lower() else int(t)


def decode_double(text: str, *, finite: bool = True) -> float:
    """A GeoCOM double. A well-formed number too large for a float (1e999) is a parse error,
    or inf with `finite=False` (the caller then judges the value, not the line)."""
    t = text.strip()
    if not _DOUBLE_RE.fullmatch(t):
        raise GeoComParseError(f"expected a GeoCOM double, got {text!r}")
    x = float(t)
    if finite and not math.isfinite(x):
        raise GeoComParseError(f"GeoCOM double out of range: {text!r}")
    return x


def decode_byte(text: str) -> int:
    m = _BYTE_RE.fullmatch(text.strip())
    if not m:
        raise GeoComParseError(f"expected a GeoCOM byte 'hh', got {text!r}")
    return int(m.group(1), 16)


def decode_string(text: str) -> str:
    t = text.strip()
    if len(t) < 2 or t[0] != '"' or t[-1] != '"':
        raise GeoComParseError(f"expected a double-quoted GeoCOM string, got {text!r}")
    body = t[1:-1]
    out: list[str] = []
    i = 0
    while i < len(body):
        ch = body[i]
        if ch == '"':
            raise GeoComParseError(f"unescaped quote inside GeoCOM string {text!r}")
        if ch != "\\":
            out.append(ch)
            i += 1
            continue
        if i + 1 >= len(body):
            raise GeoComParseError(f"dangling backslash in GeoCOM string {text!r}")
        nxt = body[i + 1]
        if nxt in "xX":
            hexpart = body[i + 2 : i + 4]
            if len(hexpart) != 2 or any(c not in "0123456789abcdefABCDEF" for c in hexpart):
                raise GeoComParseError(f"bad \\x escape in GeoCOM string {text!r}")
            out.append(chr(int(hexpart, 16)))
            i += 4
        else:
            out.append(nxt)
            i += 2
    return "".join(out)


def split_values(text: str) -> tuple[str, ...]:
    """Split a parameter list on commas outside double-quoted strings (escapes honoured)."""
    if text == "":
        return ()
    parts: list[str] = []
    cur: list[str] = []
    in_str = False
    i = 0
    while i < len(text):
        ch = text[i]
        if in_str:
            cur.append(ch)
            if ch == "\\" and i + 1 < len(text):
                cur.append(text[i + 1])
                i += 2
                continue
            if ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
            cur.append(ch)
        elif ch == ",":
            parts.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
        i += 1
    if in_str:
        raise GeoComParseError(f"unterminated string in GeoCOM parameters {text!r}")
    parts.append("".join(cur))
    return tuple(parts)


# ----------------------------------------------------------------------------- lines
@dataclass(frozen=True)
class Request:
    rpc: int
    trid: int | None
    params: tuple[str, ...]  # encoded parameter texts
    crc: int | None = None


@dataclass(frozen=True)
class Reply:
    com_rc: int
    trid: int
    rc: int
    values: tuple[str, ...]  # encoded value texts; decode with decode_* or the typed parsers
    crc: int | None = None

    @property
    def ok(self) -> bool:
        return self.com_rc == 0 and self.rc == 0

    def describe(self) -> str:
        if self.com_rc != 0:
            return "COM " + describe_return_code(self.com_rc)
        return describe_return_code(self.rc)


_REQ_RE = re.compile(r"%R1Q,(\d{1,5})(?:,(\d{1,10}))?(?:,(\d{1,5}))?:(.*)", re.DOTALL)
_REP_RE = re.compile(
    r"%R1P,(\d{1,5})(?:,(\d{1,10}))?(?:,(\d{1,5}))?:(\d{1,5})(?:,(.*))?", re.DOTALL
)


def _line_text(line: bytes | str) -> str:
    if isinstance(line, bytes | bytearray):
        if len(line) > MAX_LINE_BYTES:
            raise GeoComParseError(f"line too long ({len(line)} bytes) for GeoCOM")
        try:
            text = bytes(line).decode("ascii")
        except UnicodeDecodeError as exc:
            raise GeoComParseError(f"non-ASCII bytes in GeoCOM line: {bytes(line)[:60]!r}") from exc
    elif isinstance(line, str):
        if len(line) > MAX_LINE_BYTES:
            raise GeoComParseError(f"line too long ({len(line)} chars) for GeoCOM")
        text = line
    else:
        raise GeoComParseError(f"GeoCOM line must be bytes or str, got {type(line).__name__}")
    # the terminator is CR LF; tolerate the caller leaving it on, and a leading LF
    if text.endswith("\r\n"):
        text = text[:-2]
    elif text.endswith("\n"):
        text = text[:-1]
    text = text.lstrip("\n")
    if any(ord(c) < 0x20 or ord(c) > 0x7E for c in text):
        raise GeoComParseError(f"control characters in GeoCOM line: {text[:60]!r}")
    return text


def _check_crc(
    kind: str, text: str, m: re.Match[str], crc_group: int, expect_crc: bool
) -> int | None:
    crc_text = m.group(crc_group)
    if crc_text is None:
        if expect_crc:
            raise GeoComChecksumError(f"GeoCOM {kind} without the expected CRC field: {text!r}")
        return None
    crc = int(crc_text)
    beg, end = m.span(crc_group)
    body = text[: beg - 1] + text[end:]  # drop ",<crc>"
    if crc16(body) != crc:
        raise GeoComChecksumError(
            f"GeoCOM {kind} CRC mismatch: field {crc}, computed {crc16(body)} for {body!r}"
        )
    return crc


def format_request(
    rpc: int,
    params: tuple | list = (),
    *,
    trid: int | None = None,
    use_crc: bool = False,
    precision: int = 15,
) -> bytes:
    """One request line, terminator included. Python values are encoded by type:
    bool/int -> long, float -> double, str -> string; pre-encoded text: wrap in `Raw`."""
    if not 0 <= int(rpc) <= 65535:
        raise ValueError(f"RPC number out of range 0..65535: {rpc!r}")
    if use_crc and trid is None:
        raise ValueError("a CRC request needs a transaction id")
    enc = ",".join(encode_value(p, precision) for p in params)
    head = f"%R1Q,{int(rpc)}" + ("" if trid is None else f",{int(trid)}")
    body = f"{head}:{enc}"
    if use_crc:
        body = f"{head},{crc16(body)}:{enc}"
    return body.encode("ascii") + TERMINATOR


def parse_request(line: bytes | str, *, expect_crc: bool = False) -> Request:
    text = _line_text(line)
    m = _REQ_RE.fullmatch(text)
    if not m:
        raise GeoComParseError(f"not a GeoCOM request: {text[:80]!r}")
    crc = _check_crc("request", text, m, 3, expect_crc)
    rpc = int(m.group(1))
    if rpc > 65535:
        raise GeoComParseError(f"RPC number out of range in {text[:80]!r}")
    trid = int(m.group(2)) if m.group(2) is not None else None
    return Request(rpc=rpc, trid=trid, params=split_values(m.group(4)), crc=crc)


def format_reply(
    com_rc: int,
    trid: int,
    rc: int,
    values: tuple | list = (),
    *,
    use_crc: bool = False,
    precision: int = 15,
) -> bytes:
    enc = "".join("," + encode_value(v, precision) for v in values)
    head = f"%R1P,{int(com_rc)},{int(trid)}"
    tail = f":{int(rc)}{enc}"
    body = head + tail
    if use_crc:
        body = f"{head},{crc16(body)}{tail}"
    return body.encode("ascii") + TERMINATOR


def parse_reply(line: bytes | str, *, expect_crc: bool = False) -> Reply:
    """Parse one reply line. Raises GeoComParseError (or GeoComChecksumError) if malformed.

    A present CRC field is always verified; `expect_crc` additionally rejects a missing one.
    """
    text = _line_text(line)
    m = _REP_RE.fullmatch(text)
    if not m:
        raise GeoComParseError(f"not a GeoCOM reply: {text[:80]!r}")
    crc = _check_crc("reply", text, m, 3, expect_crc)
    trid = int(m.group(2)) if m.group(2) is not None else 0
    values = split_values(m.group(5)) if m.group(5) is not None else ()
    return Reply(com_rc=int(m.group(1)), trid=trid, rc=int(m.group(4)), values=values, crc=crc)


@dataclass(frozen=True)
class Raw:
    """An already-encoded parameter text (e.g. a byte `'0A'`)."""

    text: str


def encode_value(value: object, precision: int = 15) -> str:
    if isinstance(value, Raw):
        return value.text
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, int | np.integer):
        return encode_long(int(value))
    if isinstance(value, float | np.floating):
        return encode_double(float(value), precision)
    if isinstance(value, str):
        return encode_string(value)
    raise TypeError(f"cannot encode {type(value).__name__} as a GeoCOM value: {value!r}")


# ----------------------------------------------------------------------------- typed results
@dataclass(frozen=True)
class Coordinate:
    """Result of TMC_GetCoordinate: instrument coordinates in metres, times in ms."""

    e_m: float
    n_m: float
    h_m: float
    time_ms: int
    e_cont_m: float
    n_cont_m: float
    h_cont_m: float
    time_cont_ms: int


def decode_coordinate(reply: Reply, *, finite: bool = True) -> Coordinate:
    """Values of a TMC_GetCoordinate reply (E, N, H, CoordTime, E_c, N_c, H_c, CoordContTime).
    `finite=False`: a well-formed coordinate too large for a float decodes as inf."""
    v = reply.values
    if len(v) != 8:
        raise GeoComParseError(f"TMC_GetCoordinate reply needs 8 values, got {len(v)}: {v!r}")
    return Coordinate(
        e_m=decode_double(v[0], finite=finite),
        n_m=decode_double(v[1], finite=finite),
        h_m=decode_double(v[2], finite=finite),
        time_ms=decode_long(v[3]),
        e_cont_m=decode_double(v[4], finite=finite),
        n_cont_m=decode_double(v[5], finite=finite),
        h_cont_m=decode_double(v[6], finite=finite),
        time_cont_ms=decode_long(v[7]),
    )


def decode_single(reply: Reply, decoder: Callable[[str], T]) -> T:
    """The one value of a reply, decoded with `decoder` (e.g. `decode_long`)."""
    if len(reply.values) != 1:
        raise GeoComParseError(f"expected exactly one value, got {len(reply.values)}")
    return decoder(reply.values[0])


def p_tracker_from_enh(e_m: float, n_m: float, h_m: float) -> np.ndarray:
    """`tracker` frame position of the target: x = easting, y = northing, z = height (m)."""
    return np.array([e_m, n_m, h_m], dtype=float)


def enh_from_p_tracker(p_tracker: np.ndarray) -> tuple[float, float, float]:
    p = np.asarray(p_tracker, dtype=float)
    if p.shape != (3,):
        raise ValueError(f"p_tracker must have shape (3,), got {p.shape}")
    return float(p[0]), float(p[1]), float(p[2])
