"""MAVLink link features: signing with a key file, truth from SIM_STATE, or SIMSTATE with the SITL barometer."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from companion.config import MavlinkConfig, OriginConfig, VehicleConfig  # noqa: E402
from companion.frames import geodetic_from_ned  # noqa: E402
from companion.health import Health  # noqa: E402
from companion.mavlink.link import MavlinkLink, load_signing_key, mavlink  # noqa: E402
from sitl.truth import TruthSource  # noqa: E402
from tests.conftest import free_port  # noqa: E402

KEY = bytes(range(32))
ORIGIN = OriginConfig(lat=1.2966, lon=103.7764, alt=10.0)


def test_signing_key_file_accepts_raw_or_hex_and_rejects_other_lengths(tmp_path: Path) -> None:
    (tmp_path / "raw").write_bytes(KEY)
    (tmp_path / "hex").write_text(KEY.hex() + "\n")
    (tmp_path / "bad").write_text("short")
    assert load_signing_key(tmp_path / "raw") == KEY
    assert load_signing_key(tmp_path / "hex") == KEY
    with pytest.raises(ValueError, match="32 raw bytes or 64 hex"):
        load_signing_key(tmp_path / "bad")


def test_signed_heartbeat_is_accepted_by_a_peer_with_the_key_and_not_by_one_without() -> None:
    port_ok, port_wrong = free_port(), free_port()
    with_key = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port_ok}", source_system=1, source_component=1)
    with_key.setup_signing(KEY, sign_outgoing=True)
    wrong_key = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port_wrong}", source_system=1, source_component=1)
    wrong_key.setup_signing(bytes(32), sign_outgoing=True)

    async def main() -> None:
        for port in (port_ok, port_wrong):
            link = MavlinkLink(MavlinkConfig(), VehicleConfig(), f"udpout:127.0.0.1:{port}",
                               Health(lambda: 0.0), signing_key=KEY)
            await link._open()
            link._send_heartbeat()
            link._close()

    asyncio.run(main())
    got = with_key.recv_match(type="HEARTBEAT", blocking=True, timeout=1.0)
    assert got is not None and got.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert got.get_signed()
    assert wrong_key.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5) is None
    with_key.close()
    wrong_key.close()


def _from_autopilot(msg: mavlink.MAVLink_message) -> mavlink.MAVLink_message:
    """Pack as the autopilot (sysid 1, compid 1) and parse back, so the header is real."""
    mav = mavlink.MAVLink(None, 1, 1)
    return mav.parse_char(msg.pack(mav))


def _truth_link() -> tuple[MavlinkLink, TruthSource]:
    link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(lambda: 0.0))
    return link, TruthSource(link, ORIGIN)


def test_sim_state_becomes_ned_truth_at_the_configured_origin() -> None:
    async def main() -> TruthSource:
        link, truth = _truth_link()
        lat, lon, alt = geodetic_from_ned(np.array([3.0, -2.0, -1.5]), (ORIGIN.lat, ORIGIN.lon, ORIGIN.alt))
        link._dispatch(_from_autopilot(mavlink.MAVLink_sim_state_message(
            1, 0, 0, 0, 0, 0, 0, 0, 0, -9.8, 0, 0, 0, lat, lon, alt, 0, 0, 0.5, 0, 0,
            int(round(lat * 1e7)), int(round(lon * 1e7)))))
        return truth

    truth = asyncio.run(main())
    sample = truth.latest
    assert sample is not None
    np.testing.assert_allclose(sample.position_ned, [3.0, -2.0, -1.5], atol=0.012)  # 1e-7 deg ~ 1.1 cm
    np.testing.assert_allclose(sample.velocity_ned, [0.5, 0.0, 0.0])


def ardupilot_sitl_pressure_hpa(alt_m: float) -> float:
    """What ArduPilot SITL's noiseless barometer reads at ``alt_m`` AMSL (AP_Baro::SimpleAtmosphere, forward)."""
    h = alt_m / 1000.0 * 6369.0 / (alt_m / 1000.0 + 6369.0)
    theta = (288.15 - 6.5 * h) / 288.15
    return 101325.01576 * theta ** (34.163195 / 6.5) / 100.0


def test_simstate_takes_height_from_the_sitl_barometer_not_the_autopilot_estimate() -> None:
    async def main() -> TruthSource:
        link, truth = _truth_link()
        link._dispatch(_from_autopilot(mavlink.MAVLink_local_position_ned_message(0, 0, 0, -7.0, 0, 0, 0)))
        link._dispatch(_from_autopilot(mavlink.MAVLink_scaled_pressure_message(
            0, ardupilot_sitl_pressure_hpa(ORIGIN.alt + 2.0), 0.0, 2500)))
        lat, lon, _ = geodetic_from_ned(np.array([1.0, 1.0, 0.0]), (ORIGIN.lat, ORIGIN.lon, ORIGIN.alt))
        link._dispatch(_from_autopilot(mavlink.MAVLink_simstate_message(
            0.1, 0, 0.5, 0, 0, -9.8, 0, 0, 0, int(round(lat * 1e7)), int(round(lon * 1e7)))))
        return truth

    truth = asyncio.run(main())
    sample = truth.latest
    assert sample is not None
    np.testing.assert_allclose(sample.position_ned[:2], [1.0, 1.0], atol=0.012)
    assert sample.position_ned[2] == pytest.approx(-2.0, abs=0.002)  # float32 hPa: ~0.5 mm
    roll, _, yaw = truth.euler_at(sample.t)
    assert roll == pytest.approx(0.1, abs=1e-6) and yaw == pytest.approx(0.5, abs=1e-6)


def test_simstate_without_a_barometer_reading_gives_no_truth() -> None:
    async def main() -> TruthSource:
        link, truth = _truth_link()
        link._dispatch(_from_autopilot(mavlink.MAVLink_local_position_ned_message(0, 0, 0, -2.0, 0, 0, 0)))
        link._dispatch(_from_autopilot(mavlink.MAVLink_simstate_message(0, 0, 0, 0, 0, -9.8, 0, 0, 0, 1, 1)))
        return truth

    assert asyncio.run(main()).latest is None
