"""``epi-vo``: the command-line front end (argparse only; the work is in replay / benchmark)."""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from epi_vo.core.errors import EpiVoError

if TYPE_CHECKING:
    from epi_vo.tools.replay import ReplaySummary

# Exit codes (docs/tools.md): 0 done; 1 a verdict failed (soak, gtcheck, monitor's timeout); 2 unusable
# arguments, bag or file (one line names the problem; nothing was run); 3 the replay ran but frames were
# rejected or messages skipped (a fleet: some bag did); 4 a fleet or summary in which some bag failed
# (the counts line says how many); 129 stopped by SIGHUP, 130 by SIGINT or SIGTERM (outputs finalised at
# a frame boundary).
EXIT_INTERRUPTED = 130
EXIT_HANGUP = 129
MAX_LATENCY_RATE_HZ = 1000.0  # the fastest frame cameras; the bench publishes seconds x rate frames at that rate


def _add_replay(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="run the VO over recorded bags and write trajectory, records and a bag",
                       description="Replay a ROS 2 bag (directory or .mcap; MCAP or sqlite3) through the VO "
                                   "pipeline. Every frame is processed. One bag writes into OUTPUT; several bags "
                                   "(paths, a directory holding bags, globs) are replayed in parallel, each into "
                                   "OUTPUT/<bag name>/, with OUTPUT/summary.csv and summary.md (exit status 4 when "
                                   "a bag failed, 3 when one had problems). No output may overwrite or lie in an "
                                   "input: such a run is refused before anything is written. Exit codes, ground "
                                   "truth and recovery after a kill: docs/tools.md.")
    p.add_argument("bag", nargs="+", help="bag directory or .mcap file; several, a directory of bags or a glob "
                                          "('logs/**/*.mcap') for a fleet")
    p.add_argument("--output", "-o", required=True, help="output directory")
    p.add_argument("--jobs", "-j", type=int, default=None,
                   help="fleet: bags replayed at once, one process each (default: the number of cores)")
    p.add_argument("--force", action="store_true",
                   help="fleet: replay also the bags whose outputs are complete from an earlier run")
    p.add_argument("--params", help="ROS 2 parameter file (default: built-in defaults = config/epi_vo.yaml)")
    p.add_argument("--image-topic", help="sensor_msgs/Image or CompressedImage topic (default: the only one)")
    p.add_argument("--camera-info-topic", help="sensor_msgs/CameraInfo topic (default: the only one)")
    gt = p.add_mutually_exclusive_group()
    gt.add_argument("--gt", help="one bag: ground truth TUM file (default: the bag's PoseStamped/Odometry topic named "
                                 "as ground truth, e.g. /ground_truth/pose or /gt/odom, if there is one)")
    gt.add_argument("--gt-topic", help="the bag topic that holds ground truth (PoseStamped or Odometry); never the "
                                       "wheel odometry scale source")
    gt.add_argument("--no-gt", action="store_true", help="no ground truth, whatever the bag holds")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--rate", type=float, default=None,
                   help="one bag: hand the frames over at RATE times the pace of their stamps, as a camera would "
                        "(KLT in line; per-frame times as live; the outputs are the same). Default: flat out")
    p.add_argument("--report", action="store_true", help="also write plots and report.html into the output "
                                                         "(fleet: per bag, and OUTPUT/index.html linking them)")


def _add_summarize(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("summarize", help="summary.csv / summary.md of replay output directories (e.g. made one "
                                         "bag per cluster job)")
    p.add_argument("dirs", nargs="+", metavar="DIR",
                   help="replay output directories, or directories holding them (a fleet's OUTPUT)")
    p.add_argument("--output", "-o", default=None,
                   help="where to write the summary (default: DIR, when one is given)")
    p.add_argument("--force", action="store_true",
                   help="replace a summary there even when it lists bags this one does not")


def _add_recover(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("recover", help="make the output.mcap of a killed replay readable (its complete chunks)",
                       description="A replay killed without a chance to finish (SIGKILL, power cut) leaves an "
                                   "output.mcap without its summary. recover copies its complete chunks into a new "
                                   "output.mcap and keeps the damaged file beside it as output.mcap.damaged. "
                                   "frames.jsonl and trajectory.tum hold every frame written (docs/tools.md).")
    p.add_argument("dirs", nargs="+", metavar="DIR",
                   help="replay output directories, or directories holding them (a fleet's OUTPUT)")


def _add_benchmark(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("benchmark", help="epi_vo vs the seed article's reference pipeline on the bundled bags "
                                         "(and the KITTI clip when present), or on the scenario distribution")
    p.add_argument("--suite", choices=("bundled", "distribution", "subset"), default="bundled",
                   help="bundled: the bundled bags and the KITTI clip (default); distribution: every family x seed "
                        "of the scenario distribution and the real clips, per family (docs/distribution.md); "
                        "subset: the test suite's one short seed per family")
    p.add_argument("--bags", default=None, help="folder of bundled bags (default: the repo's bags/)")
    p.add_argument("--kitti", default=None,
                   help="KITTI clip folder (default: ../shared/data/kitti06_0-50 next to the repo, if present)")
    p.add_argument("--params", help="ROS 2 parameter file for epi_vo")
    p.add_argument("--output", default=None, help="also write the table as JSON here (bundled)")
    p.add_argument("--families", nargs="+", metavar="FAMILY", help="distribution: only these families")
    p.add_argument("--seeds", nargs="+", type=int, metavar="SEED", help="distribution: only these seeds (default 0-7)")
    p.add_argument("--jobs", type=int, default=2, help="distribution: sequences rendered and run at once (default 2)")
    p.add_argument("--cache", default=None, help="distribution: scenario cache root (default $EPI_VO_SCENARIO_CACHE "
                                                 "or ~/.cache/epi_vo/scenarios)")
    p.add_argument("--data", default=None, help="distribution: folder of the real clips (default ../shared/data)")
    p.add_argument("--no-real", action="store_true", help="distribution: leave the real clips out")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", dest="overrides",
                   help="distribution: change one parameter after --params (repeatable); with --baseline, the "
                        "run without the change, this is how a rule is judged with and without it")
    p.add_argument("--baseline", default=None, metavar="RECORD.json",
                   help="distribution: an earlier record's JSON; prints every family's figures before -> after")
    p.add_argument("--ablate", nargs="*", default=None, metavar="RULE",
                   help="distribution: run the defaults and each rule switched off (all rules, or these), and "
                        "say which pay on which family (docs/distribution.md)")
    p.add_argument("--no-reference", action="store_true",
                   help="distribution: leave the seed reference pipeline out (faster; for ablations)")
    p.add_argument("--perturb", nargs="+", type=float, default=[], metavar="REL",
                   help="distribution: also replay epi_vo on every sequence with camera_info's focal length "
                        "times 1 + REL per REL (e.g. 0.001 -0.001: a calibration nobody could tell apart) and "
                        "print each family's run-to-run spread and pooled figures")
    p.add_argument("--record-dir", default=None,
                   help="where the dated record goes (default: docs/benchmarks of the source tree)")
    p.add_argument("--no-record", action="store_true", help="print only: write no dated record")


def _add_gtcheck(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("gtcheck", help="does a bag's ground truth agree with its images? (before it judges a "
                                       "covariance: exit 1 when some pair of frames contradicts it)")
    p.add_argument("bag", help="bag directory or .mcap file")
    p.add_argument("--gt", default=None, help="ground truth, TUM (default: groundtruth_tum.txt in or beside the bag)")
    p.add_argument("--gap", type=int, default=4, help="frames between the two images of a pair (default 4)")


def _add_latency(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("latency", help="live latency of vo_node (image publish -> odometry) over DDS on loopback")
    p.add_argument("--rates", default="30,60,90,120", help="comma-separated publish rates (Hz) to try")
    p.add_argument("--seconds", type=float, default=8.0, help="duration of each rate")


def _add_monitor(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("monitor", help="live terminal view of a running vo_node (from /diagnostics)")
    p.add_argument("--once", action="store_true", help="print one snapshot and exit")
    p.add_argument("--timeout", type=float, default=None,
                   help="exit non-zero if no VO status arrived within this many seconds")
    p.add_argument("--odometry-topic", default="vo/odometry", help="odometry topic (distance travelled in metres)")
    p.add_argument("--vo-units-topic", default=None,
                   help="odometry in VO units, for the distance while there are no metres (default: vo/odometry/"
                        "vo_units in the odometry topic's namespace)")
    p.add_argument("--node-name", default=None, help="only statuses of this node ('<name>: tracking')")


def _add_report(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="plots and a self-contained HTML report of a replay output directory")
    p.add_argument("dir", help="output directory of 'epi-vo replay'")


def _add_inspect(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("inspect", help="picture of one frame pair: matches, inliers, epipolar lines, residuals")
    p.add_argument("bag", help="bag directory or .mcap file")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--frame", type=int, help="frame index (0-based, as in frames.jsonl)")
    which.add_argument("--stamp", type=float, help="image stamp in seconds (nearest frame)")
    p.add_argument("--output", "-o", default=None, help="PNG to write (default: frame_<N>.png)")
    p.add_argument("--params", help="ROS 2 parameter file for the pipeline")
    p.add_argument("--image-topic", help="image topic (default: the only one)")
    p.add_argument("--camera-info-topic", help="camera_info topic (default: the only one)")


def _add_soak(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("soak", help="many frames through the pipeline, resident memory over time and a verdict")
    p.add_argument("--frames", type=int, default=20000, help="frames to process (default 20000)")
    p.add_argument("--bag", default=None, help="bag whose frames are played forward and backward (default: "
                                               "bags/general_motion)")
    p.add_argument("--warmup", type=int, default=500, help="frames before the reference RSS sample (default 500)")
    p.add_argument("--every", type=int, default=1000, help="RSS sample interval in frames (default 1000)")
    p.add_argument("--max-growth", type=float, default=5.0, help="allowed RSS growth after warm-up, %% (default 5)")
    p.add_argument("--params", help="ROS 2 parameter file for the pipeline")


def _add_params(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("params", help="print the default parameter file (ROS 2 YAML: the node's own parameters and "
                                      "the pipeline's) with one comment per parameter")
    p.add_argument("--markdown", action="store_true",
                   help="print the parameter reference as Markdown instead (docs/parameters.md)")


def _add_play(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("play", help="publish a bag's topics vo_node consumes over ROS 2 (ros2 bag play stand-in)",
                       description="Publish the image and camera_info topics of a bag, its wheel odometry and /tf, "
                                   "/tf_static when it has them (and /clock), in real time or scaled, in the bag's "
                                   "order, as recorded. DDS settings come from the environment (ROS_DOMAIN_ID, "
                                   "ROS_AUTOMATIC_DISCOVERY_RANGE).")
    p.add_argument("bag", help="bag directory or .mcap file")
    p.add_argument("--rate", type=float, default=1.0,
                   help="speed multiplier (default 1; 0: as fast as subscribers acknowledge)")
    p.add_argument("--image-topic", help="bag topic of the images (default: the only Image/CompressedImage one)")
    p.add_argument("--camera-info-topic", help="bag topic of camera_info (default: the only one)")
    p.add_argument("--remap-image", metavar="TOPIC",
                   help="published image topic (default camera/image_raw, or camera/image_raw/compressed)")
    p.add_argument("--remap-camera-info", metavar="TOPIC",
                   help="published camera_info topic (default camera/camera_info)")
    p.add_argument("--wheel-topic", help="bag topic of the wheel odometry (default: the only nav_msgs/Odometry one "
                                         "not named as ground truth)")
    p.add_argument("--remap-wheel", metavar="TOPIC",
                   help="published wheel odometry topic (default odom, vo_node's wheel_odometry_topic)")
    p.add_argument("--namespace", default="", help="namespace of the player node (applies to relative topics)")
    p.add_argument("--clock", action="store_true", help="publish /clock with the bag time before each message")
    p.add_argument("--qos-reliability", choices=("reliable", "best_effort"), default="reliable",
                   help="default reliable (matches reliable and best-effort subscribers)")
    p.add_argument("--qos-depth", type=int, default=10, help="publisher history depth (default 10)")
    p.add_argument("--start-delay", type=float, metavar="S",
                   help="seconds to wait before playing (default: until an image subscriber matches, at most 5 s)")
    p.add_argument("--loop", action="store_true", help="play again from the start until Ctrl-C")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="epi-vo", description="Monocular visual odometry that says when a "
                                                                "pose cannot be trusted.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_replay(sub)
    _add_summarize(sub)
    _add_recover(sub)
    _add_benchmark(sub)
    _add_params(sub)
    _add_latency(sub)
    _add_monitor(sub)
    _add_report(sub)
    _add_inspect(sub)
    _add_play(sub)
    _add_soak(sub)
    _add_gtcheck(sub)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        if args.command == "replay":
            return _replay(args)
        if args.command == "summarize":
            return _summarize(args)
        if args.command == "recover":
            from epi_vo.tools.recover import run as recover_run

            return recover_run(args)
        if args.command == "benchmark":
            return _benchmark(args)
        if args.command == "monitor":
            from epi_vo.ros.monitor import run as monitor_run

            return monitor_run(args)
        if args.command == "report":
            from epi_vo.tools.report import run as report_run

            return report_run(args)
        if args.command == "inspect":
            from epi_vo.tools.inspect_frame import run as inspect_run

            return inspect_run(args)
        if args.command == "latency":
            from epi_vo.ros.live_bench import main as latency_main

            return latency_main(_latency_rates(args.rates, args.seconds), args.seconds)
        if args.command == "params" and args.markdown:
            from epi_vo.io.params_doc import parameters_markdown

            sys.stdout.write(parameters_markdown())
            return 0
        if args.command == "params":
            from epi_vo.core.config import VoConfig
            from epi_vo.io.node_options import NodeOptions
            from epi_vo.io.params import to_params_yaml

            sys.stdout.write(to_params_yaml(VoConfig(), node=NodeOptions()))
            return 0
        if args.command == "play":
            return _play(args)
        if args.command == "gtcheck":
            from epi_vo.tools.gt_check import run as gtcheck_run

            return gtcheck_run(args)
        if args.command == "soak":
            from epi_vo.tools.soak import run as soak_run

            return soak_run(args)
    except EpiVoError as exc:
        _say(f"epi-vo: error: {_one_line(str(exc))}")
        return 2
    except KeyboardInterrupt as exc:
        hangup = getattr(exc, "signum", None) == getattr(signal, "SIGHUP", None)
        _say("epi-vo: interrupted" + (" (SIGHUP: terminal closed)" if hangup else ""))
        return EXIT_HANGUP if hangup else EXIT_INTERRUPTED
    except (OSError, UnicodeError) as exc:
        # A file or directory the tools could not use and no module put into words: still one line.
        _say(f"epi-vo: error: {_describe_os_error(exc)}")
        return 2
    parser.error(f"unknown command {args.command}")
    return 2


def _latency_rates(text: str, seconds: float) -> list[float]:
    """``--rates`` as numbers, each positive, finite and at most MAX_LATENCY_RATE_HZ, with ``--seconds`` long
    enough for a frame at each; ConfigError naming the value otherwise."""
    from epi_vo.core.errors import ConfigError, quoted
    from epi_vo.io import checks

    checks.number(seconds, "--seconds", positive=True)
    rates = []
    for item in text.split(","):
        try:
            rate = float(item)
        except ValueError:
            raise ConfigError(f"--rates must be comma-separated numbers, not {quoted(item.strip())}") from None
        rates.append(checks.number(rate, "--rates", positive=True, maximum=MAX_LATENCY_RATE_HZ))
        if int(seconds * rate) < 1:
            raise ConfigError(f"--seconds {seconds:g} at {rate:g} Hz publishes no frame")
    return rates


def _benchmark(args: argparse.Namespace) -> int:
    from epi_vo.tools.bench_record import default_record_dir

    record = None if args.no_record else (Path(args.record_dir) if args.record_dir else default_record_dir())
    if args.suite == "bundled":
        for flag, given in (("--set", args.overrides), ("--baseline", args.baseline),
                            ("--no-reference", args.no_reference), ("--ablate", args.ablate is not None),
                            ("--perturb", args.perturb)):
            if given:
                _say(f"epi-vo: error: {flag} is an option of --suite distribution and subset, not of the bundled "
                     "suite")
                return 2
        from epi_vo.tools.benchmark import run_benchmark

        return run_benchmark(args.bags, args.kitti, args.params, args.output, record)
    for flag, value in (("--bags", args.bags), ("--kitti", args.kitti), ("--output", args.output)):
        if value is not None:
            _say(f"epi-vo: error: {flag} is an option of the bundled suite, not of --suite {args.suite} (its JSON "
                 "is written beside the dated record)")
            return 2
    bad = [rel for rel in args.perturb if not (math.isfinite(rel) and rel != 0.0 and abs(rel) < 0.1)]
    if bad:
        _say(f"epi-vo: error: --perturb {bad[0]:g}: a focal length change must be finite, non-zero and under "
             "10 % either way (the spread is meant for changes nobody could tell apart, ~0.001)")
        return 2
    if args.ablate is not None:
        if args.overrides or args.baseline or args.perturb:
            _say("epi-vo: error: --ablate runs its own baseline and overrides: leave --set, --baseline and --perturb "
                 "out")
            return 2
        from epi_vo.tools.ablation import run_ablation

        return run_ablation(args.suite, args.params, args.ablate, record_dir=record, families=args.families,
                            seeds=args.seeds, jobs=args.jobs, cache=args.cache, data_dir=args.data,
                            real=not args.no_real)
    from epi_vo.tools.distribution import run_distribution

    return run_distribution(args.suite, args.params, families=args.families, seeds=args.seeds, jobs=args.jobs,
                            cache=args.cache, data_dir=args.data, real=not args.no_real, record_dir=record,
                            reference=not args.no_reference, overrides=args.overrides, baseline=args.baseline,
                            perturb=args.perturb)


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _describe_os_error(exc: OSError | UnicodeError) -> str:
    if isinstance(exc, OSError):
        where = f": {exc.filename}" if exc.filename else ""
        return f"{exc.strerror or _one_line(str(exc))}{where}"
    return f"not UTF-8 text: {_one_line(str(exc))}"


def _say(line: str, *, stdout: bool = False) -> None:
    """Print one line; a terminal that went away (SIGHUP, closed pipe) does not turn it into a traceback."""
    try:
        print(line, file=sys.stdout if stdout else sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


def _replay(args: argparse.Namespace) -> int:
    from epi_vo.io import checks
    from epi_vo.io.params import load_config, load_extrinsic, load_node_options
    from epi_vo.tools.fleet_bags import is_fleet, nested_bags
    from epi_vo.tools.replay import format_summary, run_replay

    if args.rate is not None:
        checks.number(args.rate, "--rate", positive=True)
    nested = nested_bags(args.bag[0]) if len(args.bag) == 1 else []
    if nested:
        _say(f"epi-vo: error: {args.bag[0]} holds no bag itself but its sub-directories hold {len(nested)} "
             f"(e.g. {nested[0]}): replay them all with '{Path(args.bag[0]) / '*'}', or one by its path")
        return 2
    if is_fleet(args.bag):
        if args.rate is not None:
            _say("epi-vo: error: --rate paces one bag as a camera would; a fleet replays flat out")
            return 2
        return _replay_fleet(args)
    cfg = load_config(args.params)
    summary = run_replay(args.bag[0], args.output, cfg, image_topic=args.image_topic,
                         camera_info_topic=args.camera_info_topic, gt_tum=args.gt,
                         progress=not args.no_progress, rate=args.rate,
                         map_frame_id=load_node_options(args.params).map_frame_id, gt_topic=args.gt_topic,
                         no_gt=args.no_gt, inputs=[args.params] if args.params else [],
                         extrinsic=load_extrinsic(args.params))
    _say(format_summary(summary), stdout=True)
    if args.report:
        from epi_vo.tools.report import write_report

        _say(f"  report        {write_report(args.output)}", stdout=True)
    if summary.has_problems:
        _say(f"epi-vo: error: {replay_problem_line(summary)}")
        return 3
    return 0


def _replay_fleet(args: argparse.Namespace) -> int:
    from epi_vo.io import checks
    from epi_vo.io.params import load_config, load_extrinsic, load_node_options
    from epi_vo.tools.fleet import run_fleet
    from epi_vo.tools.fleet_bags import find_bags
    from epi_vo.tools.fleet_summary import exit_code

    if args.gt is not None:
        _say("epi-vo: error: --gt is the ground truth of one bag; with several bags each bag's own ground-truth "
             "topic is used (--gt-topic names it)")
        return 2
    if args.jobs is not None:
        checks.number(args.jobs, "--jobs", minimum=1)
    cfg = load_config(args.params)
    bags = find_bags(args.bag)
    result = run_fleet(bags, args.output, cfg, jobs=args.jobs, force=args.force, report=args.report,
                       progress=not args.no_progress, image_topic=args.image_topic,
                       camera_info_topic=args.camera_info_topic,
                       map_frame_id=load_node_options(args.params).map_frame_id, gt_topic=args.gt_topic,
                       no_gt=args.no_gt, inputs=[args.params] if args.params else [],
                       extrinsic=load_extrinsic(args.params))
    _print_rows(result.rows, result.summary_files)
    if result.signum is not None:
        hangup = result.signum == getattr(signal, "SIGHUP", None)
        _say("epi-vo: interrupted" + (" (SIGHUP: terminal closed)" if hangup else "") +
             ": finished bags are complete, the others are marked in their status.json")
        return EXIT_HANGUP if hangup else EXIT_INTERRUPTED
    return exit_code(result.rows)


def _summarize(args: argparse.Namespace) -> int:
    from epi_vo.tools.fleet_summary import exit_code, summarize

    rows, files = summarize(args.dirs, args.output, force=args.force)
    _print_rows(rows, files)
    return exit_code(rows)


def _print_rows(rows: Sequence[Any], files: Sequence[Any]) -> None:
    from epi_vo.tools.fleet_summary import counts_line

    for r in rows:
        s = r.summary
        figures = (f"{s.frames} frames, {s.tracked_percent:.1f} % with pose, {s.ms_per_frame:.2f} ms/frame, "
                   f"{s.end_to_end_fps:.1f} frames/s end to end" if s is not None else "")
        tail = "; ".join(x for x in (figures, r.run, r.reason) if x)
        _say(f"  {r.name:<28} {r.status.value:<11} {tail}", stdout=True)
    _say(counts_line(rows), stdout=True)
    for f in files:
        _say(f"  {f}", stdout=True)


def replay_problem_line(summary: ReplaySummary) -> str:
    """One line: how many of the frames read were rejected and the first problem, then what was skipped."""
    return summary.problem_line()


def _play(args: argparse.Namespace) -> int:
    from epi_vo.ros.play import PlayOptions, Reliability, format_summary, run_play

    options = PlayOptions(rate=args.rate, image_topic=args.image_topic, camera_info_topic=args.camera_info_topic,
                          remap_image=args.remap_image, remap_camera_info=args.remap_camera_info,
                          wheel_topic=args.wheel_topic, remap_wheel=args.remap_wheel, clock=args.clock,
                          qos_reliability=Reliability(args.qos_reliability), qos_depth=args.qos_depth,
                          start_delay_s=args.start_delay, loop=args.loop)
    print(format_summary(run_play(args.bag, options, namespace=args.namespace)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
