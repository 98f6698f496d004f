"""GeoCOM protocol layer: round trips, CRC, return codes, fuzzing of parser and driver."""

from __future__ import annotations

import numpy as np
import pytest
from geocompy.communication import crc16_bitwise as geocompy_crc16
from geocompy.geo.gctypes import GeoComCode
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from workcell.drivers import geocom as gc
from workcell.drivers.protocols import DeviceError, TrackerReading
from workcell.drivers.serial_tracker import SerialTracker

# ----------------------------------------------------------------------------- CRC


def test_crc16_arc_check_value() -> None:
    # the catalogue check value of CRC-16/ARC
    assert gc.crc16(b"123456789") == 0xBB3D
    assert gc.crc16(b"") == 0
    assert gc.crc16("123456789") == 0xBB3D


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=200))
def test_crc16_matches_independent_implementation(data: bytes) -> None:
    assert gc.crc16(data) == geocompy_crc16(data)


def test_crc_field_placement_and_coverage() -> None:
    line = gc.format_request(2082, [1000, 1], trid=7, use_crc=True)
    assert line.endswith(b"\r\n")
    text = line[:-2].decode()
    head, params = text.split(":")
    rpc_field, trid_field, crc_field = head.split(",")[1:]
    assert (rpc_field, trid_field, params) == ("2082", "7", "1000,1")
    # computed over the line without ",<crc>" and without the terminator
    assert int(crc_field) == gc.crc16(b"%R1Q,2082,7:1000,1")


def test_reply_crc_detects_any_single_digit_change() -> None:
    line = gc.format_reply(0, 12, 0, [1.25, -3.5, 0.125, 42, 1.25, -3.5, 0.125, 42], use_crc=True)
    assert gc.parse_reply(line, expect_crc=True).crc is not None
    text = line.decode()
    values_start = text.index(":")
    changed = 0
    for i in range(values_start + 1, len(text) - 2):
        if text[i].isdigit():
            d = str((int(text[i]) + 1) % 10)
            bad = (text[:i] + d + text[i + 1 :]).encode()
            with pytest.raises(gc.GeoComChecksumError):
                gc.parse_reply(bad, expect_crc=True)
            changed += 1
    assert changed > 10


def test_missing_crc_rejected_only_when_expected() -> None:
    line = gc.format_reply(0, 3, 0, [15])
    assert gc.parse_reply(line).values == ("15",)
    with pytest.raises(gc.GeoComChecksumError):
        gc.parse_reply(line, expect_crc=True)


# ----------------------------------------------------------------------------- round trips

_text = st.text(alphabet=st.characters(min_codepoint=0, max_codepoint=255), max_size=30)
_param = st.one_of(
    st.integers(min_value=-(2**31), max_value=2**31 - 1),
    st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False),
    _text,
)


@settings(max_examples=300, deadline=None)
@given(
    rpc=st.integers(0, 65535),
    trid=st.integers(0, gc.MAX_TRANSACTION_ID),
    params=st.lists(_param, max_size=8),
    use_crc=st.booleans(),
)
def test_request_round_trip(rpc: int, trid: int, params: list, use_crc: bool) -> None:
    line = gc.format_request(rpc, params, trid=trid, use_crc=use_crc)
    req = gc.parse_request(line, expect_crc=use_crc)
    assert (req.rpc, req.trid, len(req.params)) == (rpc, trid, len(params))
    for enc, value in zip(req.params, params, strict=True):
        if isinstance(value, str):
            assert gc.decode_string(enc) == value
        elif isinstance(value, int):
            assert gc.decode_long(enc) == value
        else:
            assert gc.decode_double(enc) == pytest.approx(value, rel=0, abs=1e-9)


@settings(max_examples=300, deadline=None)
@given(
    com_rc=st.sampled_from([0, 3077, 3101]),
    trid=st.integers(0, gc.MAX_TRANSACTION_ID),
    rc=st.sampled_from([int(c) for c in gc.Grc]),
    values=st.lists(_param, max_size=8),
    use_crc=st.booleans(),
)
def test_reply_round_trip(com_rc: int, trid: int, rc: int, values: list, use_crc: bool) -> None:
    rep = gc.parse_reply(gc.format_reply(com_rc, trid, rc, values, use_crc=use_crc))
    assert (rep.com_rc, rep.trid, rep.rc, len(rep.values)) == (com_rc, trid, rc, len(values))
    assert (rep.crc is not None) == use_crc
    for enc, value in zip(rep.values, values, strict=True):
        if isinstance(value, str):
            assert gc.decode_string(enc) == value


@settings(max_examples=200, deadline=None)
@given(st.floats(min_value=-1e4, max_value=1e4, allow_nan=False))
def test_double_precision_15_is_lossless_to_a_femtometre(x: float) -> None:
    assert abs(gc.decode_double(gc.encode_double(x, 15)) - x) <= 1e-12


def test_double_precision_rounds_as_requested() -> None:
    assert gc.encode_double(1.23456789, 4) == "1.2346"
    assert gc.encode_double(2.0, 15) == "2.0"
    assert gc.encode_double(-0.0, 3) == "0.0"
    with pytest.raises(ValueError):
        gc.encode_double(float("nan"))


def test_manual_examples_parse() -> None:
    # from the GeoCOM reference manual: reply to CSV_GetDateTime, bytes in 'hh' notation
    rep = gc.parse_reply(b"%R1P,0,0:0,1996,'07','19','10','13','2f'\r\n")
    assert rep.ok and rep.trid == 0
    assert [gc.decode_byte(v) for v in rep.values[1:]] == [7, 0x19, 0x10, 0x13, 0x2F]
    # the transaction id is optional in a reply
    rep = gc.parse_reply("%R1P,0:0")
    assert (rep.com_rc, rep.trid, rep.rc, rep.values) == (0, 0, 0, ())
    # a request with a leading LF (clears the instrument's buffer) and no transaction id
    req = gc.parse_request(b"\n%R1Q,5008:\r\n")
    assert (req.rpc, req.trid, req.params) == (5008, None, ())


def test_strings_with_separators_and_escapes() -> None:
    name = 'A,B "q" 100% ~x\\y\x01'
    rep = gc.parse_reply(gc.format_reply(0, 1, 0, [name, 7]))
    assert len(rep.values) == 2
    assert gc.decode_string(rep.values[0]) == name
    assert gc.decode_string('"\\x41\\X42"') == "AB"
    for bad in ['"abc', 'abc"', '"a"b"', '"a\\"', '"\\xZZ"']:
        with pytest.raises(gc.GeoComParseError):
            gc.decode_string(bad)


def test_value_decoders_reject_wrong_types() -> None:
    assert gc.decode_long("0x1F") == 31
    assert gc.decode_long("-12") == -12
    assert gc.decode_double("1e-3") == 1e-3
    for bad in ["", "1.5", "abc", "--1"]:
        with pytest.raises(gc.GeoComParseError):
            gc.decode_long(bad)
    for bad in ["", "nan", "inf", "1e999", "1,2", "x"]:
        with pytest.raises(gc.GeoComParseError):
            gc.decode_double(bad)


def test_coordinate_decoding_and_frame_mapping() -> None:
    vals = [1.5, -2.25, 0.75, 1000, 1.5001, -2.2501, 0.7501, 1010]
    coord = gc.decode_coordinate(gc.parse_reply(gc.format_reply(0, 9, 0, vals)))
    assert (coord.e_m, coord.n_m, coord.h_m, coord.time_ms) == (1.5, -2.25, 0.75, 1000)
    assert coord.time_cont_ms == 1010
    p = gc.p_tracker_from_enh(coord.e_m, coord.n_m, coord.h_m)
    np.testing.assert_array_equal(p, [1.5, -2.25, 0.75])
    assert gc.enh_from_p_tracker(p) == (1.5, -2.25, 0.75)
    with pytest.raises(gc.GeoComParseError):
        gc.decode_coordinate(gc.parse_reply(gc.format_reply(0, 9, 0, vals[:7])))
    with pytest.raises(ValueError):
        gc.enh_from_p_tracker(np.zeros(4))


# ----------------------------------------------------------------------------- return codes


def test_return_code_numbers_agree_with_geocompy() -> None:
    # geocompy's table is an independent transcription of the manual's code list
    for code in gc.RETURN_CODE_MEANING:
        assert int(code) in {int(c) for c in GeoComCode}, code
    assert GeoComCode(1283).name == "TMC_NO_FULL_CORRECTION"
    assert GeoComCode(1284).name == "TMC_ACCURACY_GUARANTEE"
    assert GeoComCode(1285).name == "TMC_ANGLE_OK"
    assert GeoComCode(1288).name == "TMC_ANGLE_NO_FULL_CORRECTION"
    assert GeoComCode(1289).name == "TMC_ANGLE_ACCURACY_GUARANTEE"
    assert GeoComCode(1292).name == "TMC_DIST_ERROR"
    assert GeoComCode(3077).name == "COM_TIMEDOUT"


def test_return_code_classes() -> None:
    assert gc.ANGLE_ONLY_CODES == {1285, 1288, 1289}
    assert gc.COORDINATE_WARNING_CODES == {1283, 1284}
    assert gc.return_code_name(1285) == "GRC_TMC_ANGLE_OK"
    assert "no distance" in gc.return_code_meaning(1285)
    assert gc.describe_return_code(3077).startswith("GRC_COM_TIMEDOUT (3077)")
    assert gc.return_code_name(54321) == "GRC_54321"
    assert gc.rpc_name(2082) == "TMC_GetCoordinate"
    rep = gc.parse_reply(b"%R1P,0,4:1285,0.0,0.0,0.0,0,0.0,0.0,0.0,0")
    assert not rep.ok and "TMC_ANGLE_OK" in rep.describe()


# ----------------------------------------------------------------------------- fuzzing

_VALID_REPLIES = [
    gc.format_reply(0, 17, 0, [1.234567891, -2.5, 0.75, 1005, 1.234567891, -2.5, 0.75, 1005]),
    gc.format_reply(0, 5, 0, [1.2, -2.5, 0.7, 100, 1.2, -2.5, 0.7, 100], use_crc=True),
    gc.format_reply(0, 3, 0, ["SIM, tracker"], use_crc=True),
    gc.format_reply(0, 2, 1285, [0.0, 0.0, 0.0, 0, 0.0, 0.0, 0.0, 0]),
    gc.format_reply(3101, 1, 0, []),
    b"%R1P,0,0:0,1996,'07','19','10','13','2f'\r\n",
]


@st.composite
def mutated_reply(draw: st.DrawFn) -> bytes:
    data = bytearray(draw(st.sampled_from(_VALID_REPLIES)))
    for _ in range(draw(st.integers(1, 6))):
        op = draw(st.sampled_from(["replace", "insert", "delete", "truncate", "dup"]))
        if not data:
            break
        i = draw(st.integers(0, len(data) - 1))
        if op == "replace":
            data[i] = draw(st.integers(0, 255))
        elif op == "insert":
            data[i:i] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del data[i]
        elif op == "truncate":
            del data[i:]
        else:
            data[i:i] = data[: draw(st.integers(0, len(data)))]
    return bytes(data)


_fuzz_line = st.one_of(st.binary(max_size=120), mutated_reply())


@settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_fuzz_line, st.booleans())
def test_parser_never_crashes_on_fuzzed_lines(line: bytes, expect_crc: bool) -> None:
    for parse in (gc.parse_reply, gc.parse_request):
        try:
            parsed = parse(line, expect_crc=expect_crc)
        except gc.GeoComParseError:
            continue
        if isinstance(parsed, gc.Reply):
            # whatever parses must decode or fail cleanly, value by value
            for v in parsed.values:
                for dec in (gc.decode_long, gc.decode_double, gc.decode_string, gc.decode_byte):
                    try:
                        dec(v)
                    except gc.GeoComParseError:
                        pass
            try:
                gc.decode_coordinate(parsed)
            except gc.GeoComParseError:
                pass


class _FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class _ScriptedSerial:
    """A serial port that answers requests with scripted actions.

    Script items are (target RPC or None for any, *action). Actions: ("valid",) a correct
    reply; ("bytes", b) raw bytes; ("mutate", [(pos, byte)]) the correct reply with bytes
    replaced ("mutate_values": in its value part only); ("drop",) nothing. Requests no item
    aims at get correct replies. Reading an empty
    input advances the fake clock by the port time-out, as a real port would block.
    """

    def __init__(self, script: list[tuple], clock: _FakeClock, timeout: float) -> None:
        self.script = list(script)
        self.clock = clock
        self.timeout = timeout
        self.inbuf = bytearray()
        self.lines = bytearray()

    @property
    def in_waiting(self) -> int:
        return len(self.inbuf)

    def read(self, n: int = 1) -> bytes:
        if not self.inbuf:
            self.clock.t += self.timeout
            return b""
        out = bytes(self.inbuf[:n])
        del self.inbuf[:n]
        return out

    def write(self, data: bytes) -> int:
        self.lines.extend(data)
        while b"\n" in self.lines:
            i = self.lines.index(b"\n")
            line = bytes(self.lines[:i]).rstrip(b"\r")
            del self.lines[: i + 1]
            if line.strip():
                self._answer(gc.parse_request(line))
        return len(data)

    def _correct(self, req: gc.Request) -> bytes:
        values: list = []
        if req.rpc == gc.Rpc.COM_GetDoublePrecision:
            values = [15]
        elif req.rpc == gc.Rpc.CSV_GetInstrumentName:
            values = ["fake"]
        elif req.rpc == gc.Rpc.TMC_GetCoordinate:
            values = [1.0, 2.0, 0.5, 7, 1.0, 2.0, 0.5, 7]
        return gc.format_reply(0, req.trid or 0, 0, values, use_crc=req.crc is not None)

    def _answer(self, req: gc.Request) -> None:
        # the first scripted action aimed at this RPC (or at any RPC) is used up
        action: tuple = ("valid",)
        for i, (target, *act) in enumerate(self.script):
            if target is None or target == req.rpc:
                action = tuple(act)
                del self.script[i]
                break
        if action[0] == "valid":
            self.inbuf.extend(self._correct(req))
        elif action[0] == "bytes":
            self.inbuf.extend(action[1])
        elif action[0] in ("mutate", "mutate_values"):
            good = bytearray(self._correct(req))
            # "mutate_values" hits the value part only (between ':' and the terminator)
            lo = good.index(b":") + 1 if action[0] == "mutate_values" else 0
            span = len(good) - 2 - lo
            for pos, byte in action[1]:
                if span > 0:
                    good[lo + pos % span] = byte
            self.inbuf.extend(good)

    def flush(self) -> None:
        pass

    def reset_input_buffer(self) -> None:
        self.inbuf.clear()

    def close(self) -> None:
        pass


_action_body = st.one_of(
    st.just(("valid",)),
    st.just(("drop",)),
    st.tuples(st.just("bytes"), _fuzz_line),
    st.tuples(
        st.sampled_from(["mutate", "mutate_values"]),
        st.lists(st.tuples(st.integers(0, 200), st.integers(0, 255)), min_size=1, max_size=3),
    ),
)
_target = st.sampled_from([None, *(int(r) for r in gc.Rpc)])
_action = st.builds(lambda target, body: (target, *body), _target, _action_body)


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(script=st.lists(_action, min_size=1, max_size=12), use_crc=st.booleans())
def test_driver_never_crashes_on_fuzzed_serial_lines(script: list[tuple], use_crc: bool) -> None:
    """250 examples x up to 12 fuzzed answers: only DeviceError or a sane reading comes out."""
    clock = _FakeClock()
    port = _ScriptedSerial(script, clock, timeout=0.05)
    trk = SerialTracker(
        "fake://",
        timeout_s=0.2,
        retries=2,
        use_crc=use_crc,
        serial_factory=lambda *a, **k: port,
        clock=clock,
    )
    try:
        trk.connect()
        for _ in range(4):
            r = trk.measure()
            assert isinstance(r, TrackerReading)
            assert r.status in ("ok", "beam_broken", "error")
            if r.status == "ok":
                assert np.all(np.isfinite(r.position_m)) and r.position_m.shape == (3,)
    except DeviceError as exc:
        assert str(exc)
    for kind, message in trk.pop_faults():
        assert isinstance(kind, str) and isinstance(message, str)
    assert trk.fault_log == []


@settings(max_examples=150, deadline=None)
@given(
    target=st.sampled_from([int(gc.Rpc.TMC_GetCoordinate), int(gc.Rpc.CSV_GetInstrumentName)]),
    mutations=st.lists(
        st.tuples(st.integers(0, 200), st.integers(0x20, 0x7E)), min_size=1, max_size=3
    ),
)
def test_driver_survives_well_framed_replies_with_bad_values(
    target: int, mutations: list[tuple[int, int]]
) -> None:
    """Printable corruption inside the values of a reply that still parses as a reply."""
    clock = _FakeClock()
    port = _ScriptedSerial([(target, "mutate_values", mutations)], clock, timeout=0.05)
    trk = SerialTracker("fake://", timeout_s=0.2, serial_factory=lambda *a, **k: port, clock=clock)
    try:
        trk.connect()
        r = trk.measure()
    except DeviceError:
        return
    # a corrupted return code is an answer the driver cannot tell from a real one (no CRC)
    assert r.status in ("ok", "beam_broken", "error")
    if r.status == "ok":
        # either the corruption was harmless (a digit for a digit) or the call was retried
        assert np.all(np.isfinite(r.position_m)) and r.position_m.shape == (3,)
