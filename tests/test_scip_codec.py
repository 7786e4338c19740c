"""SCIP 2.0 codec (drivers/scip.py): the specification's examples, round trips, bad sums,
truncations and error statuses. Expected bytes are written out by hand here (with a sum
helper of this file), not produced by the code under test."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers import scip
from drivers.scip import ChecksumError, ScipError, ScipProtocolError, SensorParams, TruncatedReply


def _sum(text: str) -> str:
    """The SCIP sum character of ``text``, computed independently of drivers.scip."""
    return chr((sum(text.encode("ascii")) & 0x3F) + 0x30)


def _line(text: str) -> str:
    return text + _sum(text) + "\n"


def _info(key: str, value: str) -> str:
    return f"{key}:{value};{_sum(f'{key}:{value}')}\n"


URG_PP = ("PP\n00P\n" + _info("MODL", "URG-04LX(Hokuyo Automatic Co., Ltd.)") + _info("DMIN", "20")
          + _info("DMAX", "5600") + _info("ARES", "1024") + _info("AMIN", "44") + _info("AMAX", "725")
          + _info("AFRT", "384") + _info("SCAN", "600") + "\n").encode("ascii")


# --- encodings and sums ------------------------------------------------------------------

@pytest.mark.parametrize(("value", "chars"), [(1234, b"CB"), (5432, b"1Dh"), (16000000, b"m2@0")])
def test_reference_encodings(value: int, chars: bytes) -> None:
    assert scip.encode(value, len(chars)) == chars
    assert scip.decode(chars) == value
    assert scip.encode_array(np.array([value]), len(chars)) == chars
    assert scip.decode_array(chars, len(chars)).tolist() == [value]


def test_status_sums() -> None:
    assert scip.sum_byte(b"00") == ord("P")
    assert scip.sum_byte(b"99") == ord("b")
    assert scip.check_line(b"00P") == b"00"
    assert scip.check_line(b"99b") == b"99"


def test_key_value_lines_pass_with_either_sum_convention() -> None:
    assert scip.check_line(b"DMIN:20;4") == b"DMIN:20;"  # ';' not summed (the specification)
    assert _sum("DMIN:20;") == "o"
    assert scip.check_line(b"DMIN:20;o") == b"DMIN:20;"  # ';' summed (some firmware)
    with pytest.raises(ChecksumError):
        scip.check_line(b"DMIN:20;5")
    assert scip.format_info_line("DMIN", "20") == b"DMIN:20;4\n"


@pytest.mark.parametrize("width", [2, 3, 4])
def test_round_trips(width: int) -> None:
    top = (1 << (6 * width)) - 1
    values = np.concatenate(([0, 1, 63, 64, top], np.random.default_rng(width).integers(0, top, 2000)))
    chars = scip.encode_array(values, width)
    assert len(chars) == width * values.size
    assert np.array_equal(scip.decode_array(chars, width), values)
    assert all(scip.decode(scip.encode(int(v), width)) == v for v in values[:50])
    assert chars[:width] == scip.encode(0, width) and chars[4 * width:5 * width] == scip.encode(top, width)


@pytest.mark.parametrize(("value", "width"), [(-1, 3), (4096, 2), (1 << 18, 3), (1 << 24, 4)])
def test_values_that_do_not_fit_are_refused(value: int, width: int) -> None:
    with pytest.raises(ValueError):
        scip.encode(value, width)
    with pytest.raises(ValueError):
        scip.encode_array(np.array([0, value]), width)


def test_invalid_characters_are_refused() -> None:
    with pytest.raises(ScipProtocolError):
        scip.decode(b"0\x7f")
    with pytest.raises(ScipProtocolError):
        scip.decode_array(b"0C/", 3)
    with pytest.raises(TruncatedReply):
        scip.decode_array(b"0CB1", 3)


# --- requests ---------------------------------------------------------------------------

def test_requests() -> None:
    assert scip.md_request(44, 725) == b"MD0044072501000\n"
    assert scip.md_request(0, 1080, cluster=3, interval=1, scans=5, two_char=True, tag="ab1") == b"MS0000108003105;ab1\n"
    assert scip.gd_request(0, 1080) == b"GD0000108001\n"
    assert scip.gd_request(10, 20, 2, two_char=True) == b"GS0010002002\n"
    assert [scip.tm_request(i) for i in range(3)] == [b"TM0\n", b"TM1\n", b"TM2\n"]
    assert (scip.QT, scip.BM, scip.VV, scip.PP, scip.II, scip.RS, scip.SCIP20) == (
        b"QT\n", b"BM\n", b"VV\n", b"PP\n", b"II\n", b"RS\n", b"SCIP2.0\n")
    assert scip.request("VV", tag="x" * 16) == b"VV;" + b"x" * 16 + b"\n"


@pytest.mark.parametrize("call", [
    lambda: scip.request("VV", tag="x" * 17), lambda: scip.request("VV", tag="a;b"),
    lambda: scip.request("VV", tag="a b"), lambda: scip.md_request(725, 44),
    lambda: scip.md_request(0, 10, cluster=100), lambda: scip.md_request(0, 10, interval=10),
    lambda: scip.md_request(0, 10, scans=100), lambda: scip.tm_request(3)])
def test_invalid_requests_are_refused(call) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError):
        call()


# --- replies ----------------------------------------------------------------------------

def _md_reply(values_text: str, stamp: str = "m2@0", echo: str = "MD0044004501000") -> bytes:
    return (f"{echo}\n99b\n" + _line(stamp) + _line(values_text) + "\n").encode("ascii")


def test_handwritten_md_reply() -> None:
    raw = _md_reply("0CB1Dh")
    data = scip.parse_distance_data(scip.split_reply(raw))
    assert data.timestamp_ms == 16000000
    assert data.ranges_mm.tolist() == [1234, 5432]
    assert data.echo == scip.DistanceEcho("MD", 44, 45, 1, 0, 0)


def test_handwritten_gs_reply() -> None:
    raw = ("GS0044004501\n00P\n" + _line("0000") + _line("CB1D") + "\n").encode("ascii")
    data = scip.parse_distance_data(scip.split_reply(raw))
    assert (data.timestamp_ms, data.ranges_mm.tolist()) == (0, [1234, 1 * 64 + 20])


def _utm_reply(ranges: np.ndarray) -> bytes:
    body = scip.format_line(scip.encode(123456, 4)) + scip.format_data_lines(ranges, 3)
    return scip.format_reply(b"MD0000108001000", "99", body)


def test_full_utm_scan_round_trip_and_block_layout() -> None:
    ranges = np.random.default_rng(1).integers(0, 60001, 1081)
    raw = _utm_reply(ranges)
    lines = raw.split(b"\n")
    data_lines = lines[3:-2]
    assert [len(line) for line in data_lines] == [65] * 50 + [43 + 1]  # 3243 characters
    assert lines[-2:] == [b"", b""]
    data = scip.parse_distance_data(scip.split_reply(raw))
    assert np.array_equal(data.ranges_mm, ranges) and data.timestamp_ms == 123456


@pytest.mark.parametrize("bad_line", [0, 17, 50])
def test_a_bad_sum_in_any_data_line_is_detected(bad_line: int) -> None:
    raw = bytearray(_utm_reply(np.full(1081, 2000)))
    data_start = raw.index(b"\n", raw.index(b"99b\n") + 4) + 1
    end_of_line = data_start + 66 * bad_line + (65 if bad_line < 50 else 44) - 1
    assert raw[end_of_line + 1] == ord("\n")
    raw[end_of_line] = ord("0") if raw[end_of_line] != ord("0") else ord("1")
    with pytest.raises(ChecksumError, match=f"data line {bad_line + 1} of 51"):
        scip.parse_distance_data(scip.split_reply(bytes(raw)))


def test_a_flipped_data_character_is_detected() -> None:
    raw = _md_reply("0CB1Dh").replace(b"0CB1Dh", b"0CC1Dh")
    with pytest.raises(ChecksumError):
        scip.parse_distance_data(scip.split_reply(raw))


def test_bad_status_and_timestamp_sums() -> None:
    with pytest.raises(ChecksumError):
        scip.split_reply(_md_reply("0CB1Dh").replace(b"99b", b"99c"))
    raw = _md_reply("0CB1Dh")
    stamp_line = _line("m2@0").encode()
    with pytest.raises(ChecksumError):
        scip.parse_distance_data(scip.split_reply(raw.replace(stamp_line, stamp_line[:4] + b"!\n")))


@pytest.mark.parametrize("raw", [
    b"MD0044004501000\n99b\n",  # no empty line
    b"MD0044004501000\n\n",  # no status line
    b"MD0044004501000\n99b\n\n",  # no timestamp
])
def test_truncated_replies(raw: bytes) -> None:
    with pytest.raises(TruncatedReply):
        scip.parse_distance_data(scip.split_reply(raw))


def test_missing_values_and_blocks_are_truncations() -> None:
    with pytest.raises(TruncatedReply, match="1 of 2"):
        scip.parse_distance_data(scip.split_reply(_md_reply("0CB")))
    with pytest.raises(TruncatedReply):  # a block cut inside a value, sum recomputed
        scip.parse_distance_data(scip.split_reply(_md_reply("0CB1D")))
    full = _utm_reply(np.full(1081, 2000))
    cut = full[:full.index(b"\n", 600) + 1] + b"\n"  # the reply ends after a few blocks
    with pytest.raises(TruncatedReply, match="of 1081"):
        scip.parse_distance_data(scip.split_reply(cut))


def test_extra_values_are_an_error() -> None:
    with pytest.raises(ScipProtocolError, match="3 range values, 2 expected"):
        scip.parse_distance_data(scip.split_reply(_md_reply("0CB1Dh0CB")))


@pytest.mark.parametrize(("command", "status", "meaning"), [
    ("MD", "01", "starting step has non-numeric value"), ("MD", "04", "end step is out of range"),
    ("MD", "05", "end step is smaller than starting step"), ("MS", "07", "number of scans has non-numeric value"),
    ("GD", "10", "laser is off"), ("MD", "21", "processing stopped"), ("MD", "49", "processing stopped"),
    ("MD", "50", "hardware trouble"), ("MD", "97", "hardware trouble"), ("MD", "98", "resumed"),
    ("BM", "02", "laser is already on"), ("TM", "04", "time requested while adjust mode is off"),
    ("QT", "0E", "time-adjust mode"), ("VV", "0D", "undefined command")])
def test_error_statuses(command: str, status: str, meaning: str) -> None:
    echo = {"MD": "MD0044004501000", "MS": "MS0044004501000", "GD": "GD0044004501"}.get(command, command)
    raw = (f"{echo}\n{status}{_sum(status)}\n\n").encode("ascii")
    reply = scip.split_reply(raw)
    with pytest.raises(ScipError, match=meaning) as err:
        if command[0] in "MG":
            scip.parse_distance_data(reply)
        else:
            reply.raise_for_status()
    assert err.value.status == status and err.value.command == command
    assert str(err.value).startswith(f"{command} status {status}: ")


def test_scip11_status_has_no_sum() -> None:
    reply = scip.split_reply(b"QT\nE\n\n")
    assert (reply.command, reply.status, reply.lines) == ("QT", "E", ())
    assert scip.split_reply(b"SCIP2.0\n0\n\n").command == "SCIP2.0"


def test_tm1_reply() -> None:
    raw = ("TM1\n00P\n" + _line("m2@0") + "\n").encode("ascii")
    assert scip.parse_timestamp_reply(scip.split_reply(raw)) == 16000000
    with pytest.raises(ScipError, match="04"):
        scip.parse_timestamp_reply(scip.split_reply(b"TM1\n04T\n\n"))


def test_pp_reply_gives_sensor_params() -> None:
    params = SensorParams.from_pp(scip.parse_info(scip.split_reply(URG_PP)))
    assert params == SensorParams("URG-04LX(Hokuyo Automatic Co., Ltd.)", 20, 5600, 1024, 44, 725, 384, 600)
    assert params.steps == 682
    assert params.scan_period_s == pytest.approx(0.1)
    assert params.step_time_s == pytest.approx(0.1 / 1024)
    assert params.step_rad == pytest.approx(2 * math.pi / 1024)
    # Sign convention of companion/messages.py: the first step is on the right (positive angle).
    assert params.angle_rad(384) == 0.0
    assert math.degrees(params.angle_rad(44)) == pytest.approx(119.53125)
    assert math.degrees(params.angle_rad(725)) == pytest.approx(-119.8828125)
    assert params.beam_steps(44, 50, 3).tolist() == [45.0, 48.0, 50.0]
    # What the emulator sends is what a sensor sends.
    fields = params.pp_fields()
    assert scip.format_reply(b"PP", "00", b"".join(scip.format_info_line(k, v) for k, v in fields.items())) == URG_PP


def test_incomplete_pp_reply() -> None:
    raw = URG_PP.replace(_info("SCAN", "600").encode(), b"")
    with pytest.raises(ScipProtocolError, match="SCAN"):
        SensorParams.from_pp(scip.parse_info(scip.split_reply(raw)))


def test_vv_reply_and_bad_info_sums() -> None:
    raw = ("VV\n00P\n" + _info("VEND", "Hokuyo Automatic Co.,Ltd.") + _info("PROD", "SOKUIKI Sensor TOP-URG UTM-30LX")
           + _info("FIRM", "1.1.3(2009)") + _info("PROT", "SCIP 2.0") + _info("SERI", "H0812345") + "\n").encode()
    fields = scip.parse_info(scip.split_reply(raw))
    assert fields["PROT"] == "SCIP 2.0" and fields["SERI"] == "H0812345" and len(fields) == 5
    with pytest.raises(ChecksumError):
        scip.parse_info(scip.split_reply(raw.replace(b"H0812345", b"H0812346")))
