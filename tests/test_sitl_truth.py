"""Simulator truth (sitl/truth.py): from ArduPilot 4.0 SITL's SIMSTATE (no velocity, no time stamp,
delivered in bursts by a TCP link) and its 10 Hz barometer, interpolated between samples, and the
built-in vehicle's SIM_STATE refined by its ATT_POS_MOCAP."""

from __future__ import annotations

import asyncio

import numpy as np

from companion import clock
from companion.clock import LockstepEventLoop
from companion.config import MavlinkConfig, OriginConfig, VehicleConfig
from companion.frames import euler_from_quat, geodetic_from_ned, quat_from_euler
from companion.health import Health
from companion.mavlink.link import MavlinkLink, mavlink
from sitl.truth import BARO_EXTRAPOLATE_S, BaroAltitude, TruthSample, TruthSource, slerp

ORIGIN = OriginConfig(lat=47.3977, lon=8.5456, alt=488.0)
SPEED_EAST_MPS = 5.0
RATE_HZ = 50
BURST = 5  # messages that arrive together, then nothing for BURST / RATE_HZ seconds


def from_autopilot(msg: mavlink.MAVLink_message) -> mavlink.MAVLink_message:
    codec = mavlink.MAVLink(None, 1, 1)
    return codec.parse_char(msg.pack(codec))


def test_simstate_velocity_is_the_vehicles_speed_when_its_messages_arrive_in_bursts() -> None:
    """Differencing two positions over their arrival times (microseconds apart in a burst) gave
    thousands of m/s; the fitted slope stays within a few percent of the true 5 m/s. The daemon's
    clock is a lockstep one, stepped between bursts, so the arrival times are exactly a burst's
    (with real sleeps a loaded machine's late wake-ups spread them and slowed the truth's speed)."""
    async def main() -> list[np.ndarray]:
        loop = asyncio.get_running_loop()
        assert isinstance(loop, LockstepEventLoop)
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        truth = TruthSource(link, ORIGIN)
        link._dispatch(from_autopilot(mavlink.MAVLink_scaled_pressure_message(0, 955.0, 0.0, 2500)))
        velocities = []
        for i in range(3 * RATE_HZ):
            lat, lon, _ = geodetic_from_ned(np.array([0.0, SPEED_EAST_MPS * i / RATE_HZ, 0.0]),
                                            (ORIGIN.lat, ORIGIN.lon, ORIGIN.alt))
            link._dispatch(from_autopilot(mavlink.MAVLink_simstate_message(
                0.0, 0.0, 0.0, 0.0, 0.0, -9.8, 0.0, 0.0, 0.0, round(lat * 1e7), round(lon * 1e7))))
            if truth.latest is not None:
                velocities.append(truth.latest.velocity_ned)
            if i % BURST == BURST - 1:
                loop.advance(loop.time() + BURST / RATE_HZ)
        return velocities

    loop = LockstepEventLoop()
    try:
        velocities = np.array(loop.run_until_complete(main()))
    finally:
        loop.close()
    settled = velocities[RATE_HZ:]  # after the first second
    assert np.all(np.abs(settled[:, 1] - SPEED_EAST_MPS) < 0.1 * SPEED_EAST_MPS)
    assert np.all(np.abs(settled[:, 0]) < 0.2)


def test_the_attitude_between_two_samples_is_interpolated_not_snapped() -> None:
    """A fixed wing rolling at 25 deg/s turns 0.5 deg between 50 Hz samples; a flow field rendered
    from the nearest sample's attitude carried up to half of that as a rotation never made."""
    async def main() -> list[tuple[float, float, float]]:
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        truth = TruthSource(link, ORIGIN)
        for t, roll_deg in ((1.0, 10.0), (1.02, 10.5)):
            truth._add(TruthSample(t, np.zeros(3), np.zeros(3), quat_from_euler(np.radians(roll_deg), 0.1, 2.0)))
        return [euler_from_quat(truth.at(1.0 + 0.02 * w).quat) for w in (0.0, 0.3, 0.7, 1.0)]

    for w, (roll, pitch, yaw) in zip((0.0, 0.3, 0.7, 1.0), asyncio.run(main())):
        assert abs(np.degrees(roll) - (10.0 + 0.5 * w)) < 1e-6
        assert abs(pitch - 0.1) < 1e-9 and abs(yaw - 2.0) < 1e-9
    halfway = slerp(quat_from_euler(0.0, 0.0, 3.1), quat_from_euler(0.0, 0.0, -3.1), 0.5)  # through 180 deg
    assert abs(abs(float(np.dot(halfway, quat_from_euler(0.0, 0.0, np.pi)))) - 1.0) < 1e-9


def _sim_state(position_ned: np.ndarray) -> mavlink.MAVLink_message:
    """The built-in vehicle's SIM_STATE at ``position_ned`` (m from ORIGIN): lat_int/lon_int in 1e-7 deg."""
    lat, lon, alt = geodetic_from_ned(position_ned, (ORIGIN.lat, ORIGIN.lon, ORIGIN.alt))
    return mavlink.MAVLink_sim_state_message(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -9.8, 0.0, 0.0, 0.0,
                                             lat, lon, alt, 0.0, 0.0, 0.0, 0.0, 0.0, round(lat * 1e7), round(lon * 1e7))


def _mocap(position_ned: np.ndarray) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_att_pos_mocap_message(0, [1.0, 0.0, 0.0, 0.0], *(float(v) for v in position_ned),
                                                 [float("nan")] + [0.0] * 20)


def test_the_position_is_the_vehicles_motion_capture_not_the_centimetre_steps_of_lat_int() -> None:
    """SIM_STATE's lat_int/lon_int step by 1.1 cm: a scanner rendering from them saw the arena up to
    5.5 mm off. The ATT_POS_MOCAP sent just before it gives the position to the micrometre; one
    that disagrees by more than a quantum (another anchor) or comes alone changes nothing."""
    true = np.array([3.4567891, -2.3456789, -1.2345678])

    async def main() -> list[np.ndarray]:
        link = MavlinkLink(MavlinkConfig(), VehicleConfig(), "udpout:127.0.0.1:9", Health(clock.now))
        truth = TruthSource(link, ORIGIN)
        positions = []
        for messages in ([_sim_state(true)], [_mocap(true), _sim_state(true)],
                         [_mocap(true + np.array([1.0, 0.0, 0.0])), _sim_state(true)],  # another anchor's frame
                         [_sim_state(true)]):  # a SIM_STATE without its own ATT_POS_MOCAP
            for msg in messages:
                link._dispatch(from_autopilot(msg))
            positions.append(truth.latest.position_ned.copy())
        return positions

    coarse, refined, other_anchor, alone = asyncio.run(main())
    assert 1e-4 < np.linalg.norm(coarse[:2] - true[:2]) < 0.01  # lat_int's steps
    assert np.linalg.norm(refined - true) < 1e-5
    assert np.allclose(other_anchor, coarse) and np.allclose(alone, coarse)


def test_arducopter_sitls_10_hz_barometer_gives_the_altitude_of_a_climb_without_its_hold_lag() -> None:
    """ArduCopter reads its barometer at 10 Hz (each reading the SITL barometer's newest sample) and
    SCALED_PRESSURE repeats the newest reading at 50 Hz. Climbing at 1 m/s, the reading held at
    each arrival was up to 9 cm behind; stamped where it was first seen and followed along its
    slope, within a centimetre."""
    climb_mps, start = 1.0, 100.0
    baro = BaroAltitude()
    errors, held = [], []
    reading = start
    for k in range(200):  # 4 s at 50 Hz
        t = 0.02 * k
        if k % 5 == 0:  # a new 10 Hz reading: the barometer's newest sample, 5 ms old
            reading = start + climb_mps * (t - 0.005)
        baro.add(t + 0.003, reading)  # arrives 3 ms after it was sent
        if k >= 10:
            now = t + 0.004  # a SIMSTATE right after
            errors.append(baro.at(now) - (start + climb_mps * now))
            held.append(reading - (start + climb_mps * now))
    assert max(abs(e) for e in errors) < 0.01
    assert min(held) < -0.08  # what the held reading was
    assert baro.at(1000.0) == baro.at(4.0 + BARO_EXTRAPOLATE_S)  # no reading for long: held, not extrapolated on


def test_arducopter_sitls_barometer_altitude_follows_a_takeoffs_acceleration_between_readings() -> None:
    """Lifting off at 5 m/s^2 to 1 m/s: the two newest readings' slope alone misses the
    acceleration by several centimetres until the readings catch up; carried by SIMSTATE's true
    acceleration, the altitude between readings stays within 5 mm."""
    ground, lift_off, accel, climb = 100.0, 1.0, 5.0, 1.0

    def altitude(t: float) -> float:
        s = min(max(t - lift_off, 0.0), climb / accel)
        return ground + 0.5 * accel * s * s + climb * max(t - lift_off - climb / accel, 0.0)

    def up_acceleration(t: float) -> float:
        return accel if lift_off <= t < lift_off + climb / accel else 0.0

    with_accel, slope_only = BaroAltitude(), BaroAltitude()
    reading = altitude(0.0)
    errors, slope_errors = [], []
    for k in range(150):  # 3 s at 50 Hz
        t = 0.02 * k
        if k % 5 == 0:  # a new 10 Hz reading: the barometer's newest sample, 5 ms old
            reading = altitude(t - 0.005)
        for baro in (with_accel, slope_only):
            baro.add(t + 0.003, reading)
        with_accel.add_acceleration(t + 0.004, up_acceleration(t))  # the SIMSTATE sent with it
        now = t + 0.004
        if k >= 10:
            errors.append(with_accel.at(now) - altitude(now))
            slope_errors.append(slope_only.at(now) - altitude(now))
    assert max(abs(e) for e in errors) < 0.005
    assert max(abs(e) for e in slope_errors) > 0.03  # what the slope alone gives


def test_arducopter_sitls_barometer_altitude_stops_where_the_vehicle_landed() -> None:
    """Descending at 0.5 m/s onto the floor at 100 m and stopping dead there: once the readings
    repeat, the altitude is the floor's, not the last descent's slope followed on below it."""
    floor, descent_mps, touchdown = 100.0, 0.5, 2.0

    def altitude(t: float) -> float:
        return floor + descent_mps * max(touchdown - t, 0.0)

    baro = BaroAltitude()
    reading = altitude(0.0)
    below = []
    for k in range(250):  # 5 s at 50 Hz
        t = 0.02 * k
        if k % 5 == 0:  # a new 10 Hz reading: the barometer's newest sample, 5 ms old
            reading = altitude(t - 0.005)
        baro.add(t + 0.003, reading)
        now = t + 0.004
        if now > touchdown + 0.3:
            below.append(floor - baro.at(now))
    assert max(below) < 0.002
