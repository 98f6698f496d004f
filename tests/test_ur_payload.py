"""The controller's payload setting read over RTDE (`UrRobot.payload_setting`): the same values as
the unmodified ur_rtde client reads, and one clear reason when a controller does not offer them,
does not answer or answers garbage (never a hang, never another exception).

Loopback addresses 127.0.0.92 (the protocol simulator) and 127.0.0.93 (fake RTDE servers)."""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytest.importorskip("rtde_receive")

import rtde_receive  # noqa: E402

from sim_devices.ur_process import SimProcess  # noqa: E402
from workcell.drivers.protocols import PayloadReadable, PayloadUnavailable  # noqa: E402
from workcell.drivers.ur_robot import UrRobot  # noqa: E402

FAKE = "127.0.0.93"


def test_payload_setting_is_what_ur_rtde_reads():
    with SimProcess("127.0.0.92", seed=5, time_scale=10.0):
        r = UrRobot("127.0.0.92", time_scale=10.0, model="ur5e")
        assert isinstance(r, PayloadReadable)
        got = r.payload_setting()  # before connect: a session of its own
        rr = rtde_receive.RTDEReceiveInterface("127.0.0.92", -1.0, ["payload", "payload_cog"])
        try:
            want_kg, want_cog = rr.getPayload(), rr.getPayloadCog()
        finally:
            rr.disconnect()
        assert got.mass_kg == want_kg and 0.0 < got.mass_kg <= 5.0
        np.testing.assert_array_equal(got.com_m, want_cog)
        r.connect()  # and again beside the driver's own receive interface
        try:
            assert r.payload_setting() == got
        finally:
            r.close()


class _FakeRtde:
    """A TCP server on FAKE:30004 that answers every packet of a connection with `reply(ptype,
    body)` -> bytes (b"" says nothing); records what it was asked."""

    def __init__(self, reply):
        self.reply = reply
        self.asked: list[int] = []
        self.srv = socket.socket()
        self.srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.srv.bind((FAKE, 30004))
        self.srv.listen(8)
        self.conns: list[socket.socket] = []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                c, _ = self.srv.accept()
            except OSError:
                return
            self.conns.append(c)
            threading.Thread(target=self._talk, args=(c,), daemon=True).start()

    def _talk(self, c):
        try:
            while True:
                head = c.recv(3)
                if len(head) < 3:
                    return
                size, ptype = struct.unpack(">HB", head)
                body = c.recv(size - 3) if size > 3 else b""
                self.asked.append(ptype)
                out = self.reply(ptype, body)
                if out:
                    c.sendall(out)
        except OSError:
            return

    def close(self):
        for s in [self.srv, *self.conns]:
            try:  # wakes the thread blocked in accept/recv, so the port is free at once
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()


def _pkt(ptype: int, body: bytes) -> bytes:
    return struct.pack(">HB", 3 + len(body), ptype) + body


def _controller(types: bytes, values: bytes):
    """An RTDE server whose output setup answers `types` and whose data packet holds `values`."""

    def reply(ptype, body):
        if ptype == ord("V"):
            return _pkt(ptype, b"\x01")
        if ptype == ord("O"):
            return _pkt(ptype, b"\x01" + types)
        if ptype == ord("S"):
            # a text message first, as a controller may send one, then the data
            return _pkt(ptype, b"\x01") + _pkt(ord("M"), b"hello") + _pkt(ord("U"), values)
        return b""

    return reply


def _robot(answer_s: float = 2.0) -> UrRobot:
    """A driver of the fake controller; a fake that answers gets 2 s to do it (its Python thread
    can lag that long on a loaded machine, which read as "no answer")."""
    return UrRobot(FAKE, connect_timeout_s=1.0, rtde_answer_timeout_s=answer_s)


def test_a_fake_controller_with_payload_outputs_is_read():
    srv = _FakeRtde(
        _controller(b"DOUBLE,VECTOR3D", b"\x01" + struct.pack(">dddd", 2.5, 0, 0, 0.07))
    )
    try:
        got = _robot().payload_setting()
        assert got.mass_kg == 2.5 and got.com_m == (0.0, 0.0, 0.07)
        assert srv.asked[:3] == [ord("V"), ord("O"), ord("S")]
    finally:
        srv.close()


@pytest.mark.parametrize(
    "reply, words",
    [
        (_controller(b"NOT_FOUND,NOT_FOUND", b""), "does not report its payload setting"),
        (lambda p, b: b"", "no answer to the payload read within 0.5 s"),
        (lambda p, b: b"HTTP/1.0 400 Bad Request\r\n\r\n", "RTDE"),
        (
            _controller(b"DOUBLE,VECTOR3D", b"\x01" + struct.pack(">dddd", float("nan"), 0, 0, 0)),
            "unreadable payload",
        ),
        (
            _controller(b"DOUBLE,VECTOR3D", b"\x01" + struct.pack(">dddd", -1.0, 0, 0, 0)),
            "unreadable payload",
        ),
    ],
    ids=["older-software", "silent", "http", "nan", "negative"],
)
def test_a_controller_that_cannot_say_is_one_line(reply, words):
    srv = _FakeRtde(reply)
    try:
        silent = words.startswith("no answer")
        t0 = time.monotonic()
        with pytest.raises(PayloadUnavailable) as ei:
            _robot(0.5 if silent else 2.0).payload_setting()
        assert time.monotonic() - t0 < (3.0 if silent else 10.0)  # the timeouts hold
        msg = str(ei.value)
        assert words in msg and FAKE in msg and "\n" not in msg, msg
    finally:
        srv.close()


@pytest.fixture(scope="module")
def garbage_server():
    current = {"bytes": b""}
    srv = _FakeRtde(lambda p, b: current["bytes"] if p == ord("V") else b"")
    yield current
    srv.close()


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.binary(min_size=0, max_size=64))
def test_any_bytes_are_a_payload_or_payload_unavailable(garbage_server, data):
    garbage_server["bytes"] = data
    r = UrRobot(FAKE, connect_timeout_s=1.0, rtde_answer_timeout_s=0.2)
    try:
        got = r.payload_setting()
    except PayloadUnavailable as e:
        assert "\n" not in str(e)
        return
    assert np.isfinite(got.mass_kg) and got.mass_kg >= 0 and np.all(np.isfinite(got.com_m))
