"""`companion` command line: run, check-config, setup-autopilot, sitl, dashboard, bench, map, laser-dots, replay,
experiment, config-reference."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import sys
from pathlib import Path
from typing import NoReturn

from companion.config import Config, ConfigError, load_config
from companion.logsetup import setup_logging

EXIT_CONFIG_ERROR = 2
# The log formats of `map build` and `replay` (companion.replay.FORMATS, written out here so that
# building the parser imports no numpy; a test keeps the two equal).
LOG_FORMATS = ("carmen", "ros", "breezyslam", "npz", "companion")


def repo_config_dir() -> Path:
    """The config/ directory shipped beside the packages (source checkout or install)."""
    return Path(__file__).resolve().parent.parent / "config"


def _config_with_logging(args: argparse.Namespace) -> Config | None:
    """The config file ``args.config`` with logging set up as it (or --log-level) says; None
    when the file is invalid (the error is printed)."""
    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        print(f"companion: {exc}", file=sys.stderr)
        return None
    setup_logging(args.log_level or cfg.logging.level)
    return cfg


def _cmd_run(args: argparse.Namespace) -> int:
    from companion.scheduling import apply_realtime_priority, single_threaded_blas

    single_threaded_blas()  # before the imports below bring numpy in
    from companion.clock import LockstepEventLoop, realtime_event_loop
    from companion.daemon import GIL_SWITCH_INTERVAL_S, Daemon

    cfg = _config_with_logging(args)
    if cfg is None:
        return EXIT_CONFIG_ERROR
    apply_realtime_priority(cfg.scheduling.realtime_priority)  # before any thread: they all inherit it
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)  # the daemon's process: see GIL_SWITCH_INTERVAL_S
    daemon = Daemon(cfg, args.mavlink)
    loop = LockstepEventLoop() if args.lockstep else realtime_event_loop()
    try:
        code = loop.run_until_complete(daemon.run())
    except ConfigError as exc:  # a file the config names (map, world, mission, signing key) is bad
        print(f"companion: {exc}", file=sys.stderr)
        code = EXIT_CONFIG_ERROR
    exit_now(code)


def exit_now(code: int) -> NoReturn:
    """End the daemon's process with ``code`` once its output is flushed, without waiting for
    threads it no longer needs. The daemon has stopped everything it owns (link, tasks,
    telemetry; a zenoh session close gets 0.4 s); Python's exit would still join every worker
    thread (a blocking call in the default executor, zenoh's own close), and an exit that hangs
    after "stopped" is one systemd has to SIGKILL."""
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _cmd_check_config(args: argparse.Namespace) -> int:
    from companion.daemon import config_warnings, load_named_files

    try:
        cfg = load_config(args.config)
        load_named_files(cfg)
        if cfg.sitl.scip_sensors:  # a config for `companion sitl` with the SCIP bridge
            from sitl.harness import check_sitl_section

            check_sitl_section(cfg)
    except ConfigError as exc:
        print(f"companion: {exc}", file=sys.stderr)
        return EXIT_CONFIG_ERROR
    for text in config_warnings(cfg):
        print(f"companion: warning: {args.config}: {text}", file=sys.stderr)
    print(f"{args.config}: OK")
    return 0


def _cmd_setup_autopilot(args: argparse.Namespace) -> int:
    from companion.setup_autopilot import parse_param_assignments, setup_autopilot

    cfg = _config_with_logging(args)
    if cfg is None:
        return EXIT_CONFIG_ERROR
    try:
        extra = parse_param_assignments(args.param)
    except ValueError as exc:
        print(f"companion: {exc}", file=sys.stderr)
        return EXIT_CONFIG_ERROR
    try:
        status, _ = asyncio.run(setup_autopilot(cfg, args.mavlink or cfg.mavlink.url, apply=args.apply,
                                                reboot=args.reboot, extra=extra, timeout_s=args.timeout,
                                                out=lambda line: print(line, flush=True)))
    except ConfigError as exc:  # the signing key file is bad
        print(f"companion: {exc}", file=sys.stderr)
        return EXIT_CONFIG_ERROR
    return status


def _cmd_sitl(args: argparse.Namespace) -> int:
    from sitl.harness import run_harness

    setup_logging(args.log_level or "info")
    return run_harness(args)


def _cmd_dashboard(args: argparse.Namespace) -> int:
    from companion.dashboard.app import run_dashboard

    cfg = _config_with_logging(args)
    if cfg is None:
        return EXIT_CONFIG_ERROR
    if args.play is not None:
        from companion.dashboard.app import run_playback

        return run_playback(Path(args.play), args.host, args.port, announce=lambda line: print(line, flush=True))
    return run_dashboard(cfg.telemetry, args.host, args.port, announce=lambda line: print(line, flush=True))


def _cmd_bench(args: argparse.Namespace) -> int:
    from companion.bench import run_bench

    return run_bench(args.repeat)


def _cmd_map_build(args: argparse.Namespace) -> int:
    from companion.mapping import build_map_file
    from companion.schema import SchemaError

    try:
        built, poses = build_map_file(args.log, args.format, args.out, args.wall_angle, args.laser, args.scan_topic,
                                      args.pose_topic)
    except (OSError, ValueError, SchemaError) as exc:
        print(f"companion map build: {exc}", file=sys.stderr)
        return EXIT_CONFIG_ERROR
    print(f"{args.out}: {len(built.walls)} walls, {len(built.corners)} corners, walls at "
          f"{built.wall_offset_deg:+.2f} deg + n x {built.wall_angle_deg} deg, "
          f"survey error {built.survey_error_m * 100:.1f} cm, "
          f"wall directions {built.wall_direction_error_deg:.2f} deg; scans placed by {poses}")
    return 0


def _cmd_laser_dots_calibrate(args: argparse.Namespace) -> int:
    from companion.beam_calibration import calibrate_recording
    from companion.nav.laser_dots.calibrate import rig_to_yaml

    cfg = _config_with_logging(args)
    if cfg is None:
        return EXIT_CONFIG_ERROR
    try:
        result = calibrate_recording(cfg, Path(args.recording))
    except (OSError, ValueError, ConfigError) as exc:
        print(f"companion laser-dots calibrate: {exc}", file=sys.stderr)
        return EXIT_CONFIG_ERROR
    c = result.calibration
    print(f"{args.recording}: {result.used} of {result.frames} frames used; frames per beam "
          f"{', '.join(str(int(n)) for n in c.count)}; line fit RMS {', '.join(f'{r * 1e3:.1f}' for r in c.rms_m)} mm; "
          f"angles between beams 0-1, 1-2, 0-2: {', '.join(f'{a:.2f}' for a in c.angles_deg)} deg", file=sys.stderr)
    text = rig_to_yaml(c.rig)
    if args.out:
        Path(args.out).write_text(text)
        print(f"{args.out}: the beams section for pipelines.laser_dots", file=sys.stderr)
    else:
        print(text, end="")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    if args.format is None and args.log.endswith(".mcap"):  # with --format ros, a ROS 2 bag in MCAP
        return _replay_recording(args)
    from companion.replay import replay_report
    from companion.schema import SchemaError
    from companion.world import load_world

    if args.format is None or args.map is None:
        print("companion replay: a scanner log needs --format and --map (a flight recording is a .mcap file)",
              file=sys.stderr)
        return EXIT_CONFIG_ERROR
    try:
        world_map = load_world(args.map)
        report = replay_report(args.log, args.format, world_map, args.map, laser=args.laser,
                               scan_topic=args.scan_topic, pose_topic=args.pose_topic,
                               odometry=args.odometry, start=args.start, seed=args.seed,
                               reference_heading_sd_deg=args.reference_heading_sd_deg)
    except (OSError, ValueError, SchemaError) as exc:
        print(f"companion replay: {exc}", file=sys.stderr)
        return EXIT_CONFIG_ERROR
    print(_written_report(report, args.report))
    return 0


def _written_report(report: dict, path: str | None) -> str:
    """``report`` as indented JSON, also written to ``path`` if given."""
    import json

    text = json.dumps(report, indent=2)
    if path:
        Path(path).write_text(text + "\n")
    return text


def _replay_recording(args: argparse.Namespace) -> int:
    """``companion replay FILE.mcap``: the recording through its pipelines (companion/recording/replay.py),
    the flight report scored again (sitl/replay_report.py: the report's module, as `companion sitl`'s)."""
    import json

    from companion.recording.reader import Recording
    from companion.recording.replay import replay, write_estimates
    from companion.schema import SchemaError
    from sitl.replay_report import replay_report

    setup_logging(args.log_level or "error")  # the pipelines' health changes are the flight's, not news
    pipelines = [p for p in (args.pipelines or "").split(",") if p] or None
    try:
        recording = Recording.open(args.log)
        result = replay(recording, pipelines, args.speed)
        report = replay_report(recording, result)
        if args.estimates:
            write_estimates(result, Path(args.estimates))
    except (OSError, ValueError, SchemaError) as exc:
        print(f"companion replay: {exc}", file=sys.stderr)
        return EXIT_CONFIG_ERROR
    _written_report(report, args.report)
    print(json.dumps(report["replay"], indent=2))
    return 0


def _cmd_experiment_faults(args: argparse.Namespace) -> int:
    from sitl.faults import run_faults

    setup_logging(args.log_level or "warning")
    return run_faults(args)


def _cmd_experiment_soak(args: argparse.Namespace) -> int:
    from sitl.soak import run_soak

    setup_logging(args.log_level or "info")
    return run_soak(args)


def _cmd_experiment_slam_recovery(args: argparse.Namespace) -> int:
    from sitl.slam_experiment import run_slam_recovery

    setup_logging(args.log_level or "warning")
    return run_slam_recovery(args)


def _cmd_config_reference(args: argparse.Namespace) -> int:
    from companion.config_reference import render

    print(render(), end="")
    return 0


def _add_topic_arguments(parser: argparse.ArgumentParser) -> None:
    """--scan-topic and --pose-topic: which topics of a ROS bag (drivers.lidar_replay.read_ros_bag)."""
    parser.add_argument("--scan-topic", help="ros: the sensor_msgs/LaserScan topic (default: the bag's only one); "
                                             "companion: the scanner's /sensors/<name> (default: the only one)")
    parser.add_argument("--pose-topic", help="ros: the reference poses, a nav_msgs/Odometry or geometry_msgs/"
                                             "PoseStamped topic (default: the bag's only one; none if several)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="companion", description=__doc__)
    parser.add_argument("--log-level", choices=["debug", "info", "warning", "error"], help="override the config's level")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run the daemon (what systemd starts)")
    run.add_argument("-c", "--config", required=True, help="YAML config file")
    run.add_argument("--mavlink", help="autopilot endpoint, pymavlink syntax (overrides mavlink.url)")
    run.add_argument("--lockstep", action="store_true",
                     help="clock driven by the SITL vehicle's TIMESYNC ticks (used by `companion sitl --lockstep`)")
    run.set_defaults(func=_cmd_run)

    check = sub.add_parser("check-config", help="validate a config file (exit 2 on error)")
    check.add_argument("config")
    check.set_defaults(func=_cmd_check_config)

    setup = sub.add_parser("setup-autopilot", help="check (and with --apply write) the autopilot parameters the "
                                                    "configured pipelines need; dry run by default")
    setup.add_argument("-c", "--config", required=True, help="YAML config file (its pipelines decide what is needed)")
    setup.add_argument("--mavlink", help="autopilot endpoint, pymavlink syntax (overrides mavlink.url)")
    setup.add_argument("--apply", action="store_true", help="write the differing parameters (PARAM_SET, read back)")
    setup.add_argument("--reboot", action="store_true",
                       help="after --apply, reboot the autopilot (disarmed only) if a written parameter needs it")
    setup.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                       help="also set this parameter (repeatable)")
    setup.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the autopilot and its parameters")
    setup.set_defaults(func=_cmd_setup_autopilot)

    sitl = sub.add_parser("sitl", help="simulated vehicle + daemon over loopback; optional scored report")
    sitl.add_argument("-c", "--config", default=str(repo_config_dir() / "sitl.yaml"), help="daemon config (default: config/sitl.yaml)")
    sitl.add_argument("--mission", help="mission name: missions/NAME.yaml beside the config file (default: the config's mission)")
    sitl.add_argument("--seconds", type=float, help="simulated seconds to run (default: until Ctrl-C; with --report, "
                                                    "until the mission is over)")
    sitl.add_argument("--lockstep", action="store_true", help="deterministic simulated clock")
    sitl.add_argument("--seed", type=int, default=0)
    sitl.add_argument("--report", help="write the truth-scored flight report (JSON) here")
    sitl.add_argument("--record", metavar="DIR", help="record the flight (record: section, enabled) into DIR "
                                                      "(*.mcap; with --report, also what the report was scored from, "
                                                      "for `companion replay`)")
    sitl.add_argument("--control-law", choices=["rpt", "pid"], help="fly trajectories with this law (overrides control.law)")
    sitl.add_argument("--autopilot", help="use an external autopilot SITL at this pymavlink URL instead of the built-in "
                                          "vehicle (no truth: no --report)")
    sitl.add_argument("--ardupilot", metavar="PATH", help="run this ArduPilot SITL binary as the vehicle, set up by "
                                                          "the companion (overrides sitl.ardupilot.binary; real time)")
    sitl.add_argument("--dashboard", type=int, nargs="?", const=8080, metavar="PORT",
                      help="also serve the live telemetry page on 127.0.0.1:PORT (default 8080) and print its URL")
    sitl.set_defaults(func=_cmd_sitl)

    dash = sub.add_parser("dashboard", help="live telemetry page for a ground laptop (read-only; joins zenoh)")
    dash.add_argument("-c", "--config", default=str(repo_config_dir() / "sitl.yaml"),
                      help="config whose telemetry section says where to connect (default: config/sitl.yaml)")
    dash.add_argument("--host", default="127.0.0.1", help="address to serve the page on (default: loopback only)")
    dash.add_argument("--port", type=int, default=8080, help="HTTP port (0: any free port; default 8080)")
    dash.add_argument("--play", metavar="FILE.mcap", help="play a flight recording (any of its parts) on the page "
                                                      "instead of joining zenoh: play, pause, seek, speed")
    dash.set_defaults(func=_cmd_dashboard)

    bench = sub.add_parser("bench", help="per-stage timings (median, p99) of every pipeline present")
    bench.add_argument("--repeat", type=int, default=2000)
    bench.set_defaults(func=_cmd_bench)

    mapping = sub.add_parser("map", help="lidar maps of a user's own building")
    maps = mapping.add_subparsers(dest="map", required=True)
    build = maps.add_parser("build", help="build a map (world YAML for pipelines.lidar.map) from a log: placed with "
                                          "its poses, or by scan matching when it has none")
    build.add_argument("log", help="the log (e.g. a CARMEN log, plain or .gz; a ROS 1 .bag, a ROS 2 bag directory; "
                                   "a recording of this daemon, .mcap)")
    build.add_argument("--format", required=True, choices=LOG_FORMATS,
                       help="the log's format (carmen, and ros with a pose topic, carry poses; the others are placed by "
                            "scan matching)")
    build.add_argument("--out", required=True, help="write the map (world YAML) here")
    build.add_argument("--wall-angle", type=int, choices=[90, 45, 30], default=90,
                       help="the building's walls run at multiples of this angle (default 90)")
    build.add_argument("--laser", choices=["front", "rear"], default="front", help="carmen: which laser's messages")
    _add_topic_arguments(build)
    build.set_defaults(func=_cmd_map_build)

    dots = sub.add_parser("laser-dots", help="tools of the three-laser-dot pipeline (pipelines.laser_dots)")
    dots_tools = dots.add_subparsers(dest="laser_dots", required=True)
    calibrate = dots_tools.add_parser("calibrate", help="the beams' origins and directions from a recording of the "
                                                        "downward camera over the floor markers "
                                                        "(companion/beam_calibration.py)")
    calibrate.add_argument("-c", "--config", required=True, help="the config with the pipelines.laser_dots section")
    calibrate.add_argument("recording", help="a folder of .png / .jpg frames (name order) or a video file")
    calibrate.add_argument("--out", help="write the beams section (YAML) here instead of to stdout")
    calibrate.set_defaults(func=_cmd_laser_dots_calibrate)

    replay = sub.add_parser("replay", help="replay a flight recording (.mcap) through its pipelines against the "
                                           "recorded estimates (companion/recording/replay.py), or a scanner log "
                                           "through the lidar localizer, scored against the log's own poses "
                                           "(companion/replay.py)")
    replay.add_argument("log", help="a flight recording (FILE.mcap, any part of it), or a scanner log (e.g. a CARMEN "
                                    "log, plain or .gz; a ROS 1 .bag, a ROS 2 bag directory)")
    replay.add_argument("--report", help="also write the report (JSON) here")
    replay.add_argument("--pipelines", help="recording: replay only these pipelines (comma-separated; default all)")
    replay.add_argument("--speed", type=float, help="recording: replay at this multiple of recorded time "
                                                    "(default: as fast as it runs)")
    replay.add_argument("--estimates", metavar="OUT.mcap", help="recording: write the replayed estimates next to the "
                                                                "recorded ones (MCAP, to open in Foxglove)")
    replay.add_argument("--log-level", choices=["debug", "info", "warning", "error"])
    replay.add_argument("--format", choices=LOG_FORMATS, help="scanner log: its format")
    replay.add_argument("--map", help="scanner log: the map (world YAML, e.g. from `companion map build`)")
    replay.add_argument("--laser", choices=["front", "rear"], default="front", help="carmen: which laser's messages")
    _add_topic_arguments(replay)
    replay.add_argument("--odometry", choices=["auto", "log", "noisy", "none"], default="auto",
                        help="motion between scans: the log's odometry, with simulated wheel errors, or none "
                             "(default auto: noisy when the log's odometry is its reference)")
    replay.add_argument("--start", choices=["reference", "relocalize", "map"], default="reference",
                        help="start at the log's first reference pose (default), relocalize from nothing, or at the "
                             "map's start (map build sets it to the first scan's pose: the walk it was built from)")
    replay.add_argument("--seed", type=int, default=0, help="seed of the simulated wheel-odometry errors")
    replay.add_argument("--reference-heading-sd-deg", type=float, default=0.0, metavar="DEG",
                        help="scanner log: the reference poses' own 1-sigma heading error, degrees, counted in "
                             "heading_nees_mean (default 0: the reference taken as exact)")
    replay.set_defaults(func=_cmd_replay)

    experiment = sub.add_parser("experiment", help="experiments against the SITL that print figures")
    experiments = experiment.add_subparsers(dest="experiment", required=True)
    faults = experiments.add_parser("faults", help="the fault suite (real time, about 5 minutes): hostile and broken "
                                                   "inputs at every edge, recovery of each (sitl/faults.py)")
    faults.add_argument("--out", required=True, help="write the results (JSON) here")
    faults.add_argument("-c", "--config", default=str(repo_config_dir() / "sitl-real-driver.yaml"),
                        help="SITL config with the scanners behind the SCIP bridge (default: config/sitl-real-driver.yaml)")
    faults.add_argument("--only", help="comma-separated fault names (default: all)")
    faults.add_argument("--seed", type=int, default=0)
    faults.set_defaults(func=_cmd_experiment_faults)
    soak = experiments.add_parser("soak", help="a long real-time flight: the daemon's memory and rates over time "
                                               "(sitl/soak.py)")
    soak.add_argument("--out", required=True, help="write the samples and the summary (JSON) here")
    soak.add_argument("--seconds", type=float, default=3600.0, help="how long to sample the hold (the mission holds 30 s longer; default 3600)")
    soak.add_argument("-c", "--config", default=str(repo_config_dir() / "sitl-real-driver.yaml"),
                      help="SITL config (default: config/sitl-real-driver.yaml)")
    soak.add_argument("--seed", type=int, default=0)
    soak.set_defaults(func=_cmd_experiment_soak)
    slam = experiments.add_parser("slam-recovery", help="the EKF-SLAM return-to-base paper's three simulations as a "
                                                        "seeded Monte-Carlo, no SITL (sitl/slam_experiment.py)")
    slam.add_argument("--seeds", type=int, default=30, help="number of seeds (default 30)")
    slam.add_argument("--seed", type=int, default=0, help="first seed (default 0)")
    slam.add_argument("--out", required=True, help="write the results (JSON) here")
    slam.add_argument("--variant", choices=["reference", "larger-loop"], default="reference",
                      help="circles around a reference landmark (default) or the larger loops of the paper's Figs. 7-8")
    slam.add_argument("--submap-keep", choices=["in_view", "start"], default="in_view",
                      help="a new sub-map keeps the landmarks in view at its start (default) or only the start "
                           "landmark (the paper's STEP 6)")
    slam.set_defaults(func=_cmd_experiment_slam_recovery)

    ref = sub.add_parser("config-reference", help="print the config reference (docs/config.md)")
    ref.set_defaults(func=_cmd_config_reference)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
