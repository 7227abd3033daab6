"""Command-line wiring of the gateway: ``gateway`` and ``calibrate``."""

from __future__ import annotations

import argparse
import json
import math
import sys
from contextlib import suppress
from pathlib import Path

from bodynet.core import keys
from bodynet.core.keys import BRANCHES, branch_named
from bodynet.core.subject import Profile, ProfileError
from bodynet.gateway import shards
from bodynet.session import (
    DEFAULT_ROUTER,
    add_session_args,
    argtypes,
    config_from_args,
    open_session,
)

#: Poses per second: the solver's own pace, at most 1 kHz.
POSE_RATE_HZ = argtypes.bounded_float(0.1, 1000.0, "poses per second, 0.1 to 1000")


def _profile(path: Path | None) -> Profile:
    from bodynet.session import profile_file

    if path is None or not path.exists():
        return Profile()
    return profile_file.load(path)


def cmd_gateway(args: argparse.Namespace) -> int:
    from bodynet.session.memory import limit_malloc_arenas

    limit_malloc_arenas()  # before any thread (numpy's, Zenoh's) takes an arena of its own
    from bodynet.cli.nodes import stop_on_signals
    from bodynet.gateway.service import Gateway

    try:
        profile = _profile(args.profile)
    except ProfileError as exc:
        print(f"bodynet gateway: {exc}", file=sys.stderr)
        return 2
    if (args.mode or "router") == "router" and not args.listen and not args.config:
        args.listen = [DEFAULT_ROUTER]
    if args.all_subjects and args.subject:
        print("bodynet gateway: --all-subjects or --subject, not both", file=sys.stderr)
        return 2
    if args.share is not None and not args.all_subjects:
        print("bodynet gateway: --share shares the subjects of --all-subjects; give both",
              file=sys.stderr)  # fmt: skip
        return 2
    stop = stop_on_signals()
    session = open_session(config_from_args(args))
    branches = [branch_named(b) for b in args.branch] or None
    share = None if args.share is None else (args.share or shards.new_id())
    gateway = Gateway(session, profile, args.profile, branches, args.rate_hz,
                      all_subjects=args.all_subjects, profile_dir=args.profile_dir,
                      share=share)  # fmt: skip
    where = ", ".join(args.listen) if args.listen else "its router"
    served = (
        "every subject (<subject>/body/...)"
        if args.all_subjects
        else f"subject {args.subject or profile.subject!r}"
    )
    if gateway.share is not None:
        served = f"its share of every subject (gateway {gateway.share.id})"
    print(f"bodynet gateway: {served}, serving on {where}; "
          f"poses on {keys.pose_key()} and {keys.all_poses()}", flush=True)  # fmt: skip
    try:
        gateway.run(stop)
    finally:
        gateway.close()
        session.close()
    if gateway.session_lost:
        print("bodynet gateway: the Zenoh session closed under the gateway; stopped",
              file=sys.stderr)  # fmt: skip
        return 1
    return 0


def cmd_subjects(args: argparse.Namespace) -> int:
    """One JSON line per subject on the network: its live nodes (liveliness
    tokens) and branches, and whether a gateway answers for it."""
    session = open_session(config_from_args(args))
    nodes: dict[str | None, set[str]] = {}
    served: set[str | None] = set()
    try:
        for prefix in ("", keys.ANY_SUBJECT + "/"):
            for reply in session.liveliness().get(prefix + keys.all_raw(), timeout=args.timeout):
                if reply.ok is not None:
                    with suppress(keys.KeySpaceError):
                        name, key = keys.split_subject(str(reply.ok.key_expr))
                        nodes.setdefault(name, set()).add(key)
            for reply in session.get(prefix + keys.TOPOLOGY, timeout=args.timeout):
                if reply.ok is not None:
                    with suppress(keys.KeySpaceError):
                        served.add(keys.split_subject(str(reply.ok.key_expr))[0])
    finally:
        session.close()
    for name in sorted(nodes.keys() | served, key=lambda n: n or ""):
        live = nodes.get(name, set())
        branches = sorted({str(keys.parse(k)[0].branch) for k in live if _is_site(k)})
        print(json.dumps({"subject": name, "nodes": len(live), "branches": branches,
                          "gateway": name in served}))  # fmt: skip
    if not nodes and not served:
        print("bodynet subjects: no subject on the network", file=sys.stderr)
    return 0


def _is_site(key: str) -> bool:
    try:
        keys.parse(key)
    except keys.KeySpaceError:
        return False
    return True


def _reference_arg(text: str) -> tuple[str, str]:
    """``sacrum:+z`` or ``body/trunk/mid/sacrum/raw:+z`` -> (raw key, axis)."""
    from bodynet.core.profile import IMU_SITES
    from bodynet.core.subject import AXES

    where, _, axis = text.rpartition(":")
    named = {s.name: s.raw_key for s in IMU_SITES.values() if s.branch == keys.TRUNK}
    named.update({f"{s.branch}/{s.name}": s.raw_key for s in IMU_SITES.values()})
    key = named.get(where, where)
    try:
        keys.parse(key)
    except keys.KeySpaceError:
        key = ""
    if not key or axis.lower() not in AXES:
        raise argparse.ArgumentTypeError(
            f"a heading reference is TAG:AXIS, e.g. sacrum:+z or left-leg/thigh:-y (the tag's "
            f"axis that pointed forward in calibration; axes {', '.join(AXES)}), not {text!r}"
        )
    return key, axis.lower()


def add_heading_args(p: argparse.ArgumentParser) -> None:
    """The calibration pose and what is known of the tags' heading (profile overrides)."""
    from bodynet.core.subject import DRIFT_MODES, HEADING_MODES, POSES

    p.add_argument("--pose", choices=POSES, default=None,
                   help="the still calibration pose: tpose (arms out, palms down) or npose "
                        "(arms down, palms to the thighs); remembered in the profile "
                        "(default: the profile's, tpose)")  # fmt: skip
    p.add_argument("--heading", choices=HEADING_MODES, default=None,
                   help="auto: the tags share one heading (magnetometer-based sensors) and the "
                        "subject faces anywhere: found from a knee's or elbow's motion after "
                        "the pose; fixed: the subject faced +X of the tags' frame; "
                        "independent: 6-axis tags each with its own (the legs' found from a "
                        "walk, the arms' from a reach, the trunk's from a bow) "
                        "(default: the profile's, auto)")  # fmt: skip
    p.add_argument(
        "--heading-reference",
        type=_reference_arg,
        default=None,
        metavar="TAG:AXIS",
        help="declared: this tag's axis pointed forward in the pose, e.g. sacrum:+z",
    )
    p.add_argument("--drift", choices=DRIFT_MODES, default=None,
                   help="which joints hold drifting tags' headings: hinges (knees, ankles, "
                        "elbows, wrists), joints (and the hips', shoulders', lumbar's and "
                        "neck's twist: 6-axis tags), off; auto: joints with --heading "
                        "independent, else hinges (default: the profile's, auto)")  # fmt: skip


def with_heading_args(profile: Profile, args: argparse.Namespace) -> Profile:
    """``profile`` with the command line's heading options over its own."""
    from dataclasses import replace

    changes: dict[str, object] = {}
    if getattr(args, "heading", None):
        changes["heading"] = args.heading
    if getattr(args, "heading_reference", None):
        changes["heading_reference"] = args.heading_reference
    if getattr(args, "pose", None):
        changes["pose"] = args.pose
    if getattr(args, "drift", None):
        changes["drift"] = args.drift
    return replace(profile, **changes) if changes else profile  # type: ignore[arg-type]


def cmd_calibrate_tpose(args: argparse.Namespace) -> int:
    if args.from_ is not None:
        return _calibrate_from_recording(args)
    options = (("--heading", args.heading), ("--drift", args.drift),
               ("--heading-reference", args.heading_reference))  # fmt: skip
    given = [flag for flag, value in options if value]
    if given:  # a live gateway solves with its own profile's: never silently ignored
        print(f"bodynet calibrate tpose: {', '.join(given)} go with --from (into --profile); "
              "a live gateway takes them from the profile it was started with",
              file=sys.stderr)  # fmt: skip
        return 2
    query = f"{keys.CALIBRATE_TPOSE}?seconds={args.seconds}" + (
        f";pose={args.pose}" if args.pose else "")  # fmt: skip
    return _ask_gateway(args, "tpose", query, 10.0 + 2 * args.seconds)


def cmd_calibrate_yaw(args: argparse.Namespace) -> int:
    """``calibrate yaw``: the yaw reset of the live gateway (the subject faces
    forward now); its JSON answer printed, exit 1 if refused or unanswered."""
    return _ask_gateway(args, "yaw", keys.CALIBRATE_YAW, 10.0)


def _ask_gateway(args: argparse.Namespace, what: str, query: str, timeout: float) -> int:
    """Ask the live gateway's calibration ``query``; print its JSON answer (and
    a refusal's reason, or the headings a calibration dropped, on stderr)."""
    session = open_session(config_from_args(args))
    try:
        replies = list(session.get(query, timeout=timeout))
    finally:
        session.close()
    for reply in replies:
        if reply.ok is not None:
            result = json.loads(reply.ok.payload.to_bytes())
            print(json.dumps(result, indent=2))
            if not result.get("ok"):
                print(f"bodynet calibrate: refused: {result.get('error')}", file=sys.stderr)
            else:
                from bodynet.gateway.heading import dropped_note

                if note := dropped_note(result):
                    print(f"bodynet calibrate: {note}", file=sys.stderr)
            return 0 if result.get("ok") else 1
    print(f"bodynet calibrate {what}: no gateway answered", file=sys.stderr)
    return 1


def _calibrate_from_recording(args: argparse.Namespace) -> int:
    """``calibrate tpose --from REC --window A:B --profile P``: the mounts from a
    still window of a recording, written into the profile; a refusal (subject
    moved, too short, a tag missing) prints why, exits 1 and leaves it as it was."""
    from bodynet.clients.mcap_store import StoreError
    from bodynet.gateway.heading import CalibrationRefused, dropped_note
    from bodynet.nodes.captures import CaptureError, capture_options
    from bodynet.nodes.sources.base import CaptureStats
    from bodynet.offline.process import calibrate_recording, recorded_samples
    from bodynet.session import profile_file

    if args.profile is None:
        print("bodynet calibrate tpose: --from needs --profile (the file the mounts go into)",
              file=sys.stderr)  # fmt: skip
        return 2
    try:
        profile = with_heading_args(_profile(args.profile), args)
        samples = recorded_samples(args.from_, args.format, CaptureStats(), None,
                                   capture_options(args))  # fmt: skip
        result = calibrate_recording(samples, profile, args.window or (0.0, args.seconds),
                                     args.pose)  # fmt: skip
        profile_file.save(result.apply(profile, args.pose), args.profile)
        note = dropped_note(result.report)
    except CalibrationRefused as exc:
        print(json.dumps({"ok": False, "error": str(exc), **exc.report}, indent=2))
        print(f"bodynet calibrate tpose: refused: {exc}; {args.profile} is unchanged",
              file=sys.stderr)  # fmt: skip
        return 1
    except (ProfileError, OSError, ValueError, CaptureError, StoreError) as exc:
        print(f"bodynet calibrate tpose: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({**result.report, "profile": str(args.profile)}, indent=2))
    if note:
        print(f"bodynet calibrate tpose: {note}", file=sys.stderr)
    return 0


def add_gateway_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--profile", type=argtypes.input_or_new_file,
                   help="subject profile (TOML); created by calibration")  # fmt: skip
    p.add_argument("--branch", action="append", default=[], choices=[str(b) for b in BRANCHES],
                   help="serve only these branches (repeatable; default all)")  # fmt: skip
    p.add_argument("--rate-hz", type=POSE_RATE_HZ, default=100.0, help="most poses per second")
    p.add_argument("--all-subjects", action="store_true",
                   help="serve every subject on the network, each a body of its own")  # fmt: skip
    p.add_argument("--profile-dir", type=argtypes.output_dir,
                   help="with --all-subjects: <subject>.toml profiles (default.toml "
                        "without namespace), written by T-pose calibration")  # fmt: skip
    p.add_argument("--share", nargs="?", const="", metavar="ID", type=_gateway_id,
                   help="with --all-subjects: share the subjects with the other gateways "
                        "started with --share (each serves its own; a dead one's are "
                        "taken over); ID names this one (default: host, pid, random)")  # fmt: skip
    add_session_args(p, default_mode="router")


def _gateway_id(text: str) -> str:
    if not text:
        return text
    try:
        return shards.check_id(text)
    except keys.KeySpaceError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_subjects_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--timeout", type=argtypes.bounded_float(0.01, 600.0, "seconds"), default=2.0,
                   help="seconds to wait for answers")  # fmt: skip
    add_session_args(p)


def add_calibrate_args(cal: argparse.ArgumentParser) -> None:
    csub = cal.add_subparsers(dest="what", required=True, metavar="WHAT")
    from bodynet.nodes.captures import add_capture_args, formats

    p = csub.add_parser("tpose", help="IMU mounts: the subject stands still in the T-pose "
                                      "(or --pose npose)")  # fmt: skip
    p.add_argument("--seconds", type=argtypes.bounded_float(0.1, 60.0, "seconds of still pose"),
                   default=1.0, help="still window to average")  # fmt: skip
    p.add_argument("--from", dest="from_", type=argtypes.input_file, default=None,
                   metavar="RECORDING",
                   help="calibrate from a recording (MCAP, or a capture of --format) instead "
                        "of the live gateway; needs --profile")  # fmt: skip
    p.add_argument("--window", type=argtypes.time_window, default=None, metavar="START:END",
                   help="with --from: the still window, seconds from the recording's start "
                        "(default 0:--seconds)")  # fmt: skip
    p.add_argument(
        "--format",
        choices=formats(),
        default=None,
        help="with --from: the capture's format (default: from its suffix, .mcap, .sto, "
        ".csv, .log...)",
    )
    add_capture_args(p)
    p.add_argument("--profile", type=argtypes.input_or_new_file,
                   help="with --from: the profile to write")  # fmt: skip
    add_heading_args(p)
    add_session_args(p)
    p.set_defaults(func=cmd_calibrate_tpose)
    p = csub.add_parser("yaw", help="yaw reset: the subject faces forward now (the live "
                                    "gateway; its heading must be known)")  # fmt: skip
    add_session_args(p)
    p.set_defaults(func=cmd_calibrate_yaw)
    add_calibrate_ole_parser(csub)
    add_calibrate_assign_parser(csub)


def _tracker_arg(text: str) -> str:
    from bodynet.core.codecs.slimevr import normalise_tracker_id

    try:
        return normalise_tracker_id(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _site_arg(text: str) -> keys.Site:
    try:
        return keys.site_named(text)
    except keys.KeySpaceError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_calibrate_assign_parser(csub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = csub.add_parser("assign", help="put a tracker (SlimeVR: MAC-sensor) on a site")
    p.add_argument("tracker", type=_tracker_arg,
                   help="the tracker's id, e.g. aabbccddeeff-0 (body/@topology lists "
                        "unassigned ones)")  # fmt: skip
    p.add_argument("site", type=_site_arg, help="where it sits, e.g. left-arm/upperarm")
    p.add_argument("--profile", type=argtypes.input_or_new_file,
                   help="also keep it in this profile (TOML)")  # fmt: skip
    p.add_argument("--offline", action="store_true",
                   help="only write the profile; tell no running bridge")  # fmt: skip
    p.add_argument("--timeout", type=argtypes.bounded_float(0.01, 600.0, "seconds"), default=3.0,
                   help="seconds to wait for a bridge to publish the site")  # fmt: skip
    add_session_args(p)
    p.set_defaults(func=cmd_calibrate_assign)


def cmd_calibrate_assign(args: argparse.Namespace) -> int:
    """Save the assignment in the profile, and tell the running bridges: the
    tracker's samples then come on the site's key."""
    import time

    name = keys.site_name(args.site)
    if args.profile is not None:
        from bodynet.session import profile_file

        try:
            profile = _profile(args.profile).with_tracker(args.tracker, name)
            profile_file.save(profile, args.profile)
        except (ProfileError, OSError) as exc:
            print(f"bodynet calibrate assign: {exc}", file=sys.stderr)
            return 2
        print(f"{args.tracker} -> {name}: saved in {args.profile}", file=sys.stderr)
    elif args.offline:
        print("bodynet calibrate assign: --offline needs --profile", file=sys.stderr)
        return 2
    if args.offline:
        return 0
    session = open_session(config_from_args(args))
    try:
        session.put(keys.ASSIGN, json.dumps({"tracker": args.tracker, "site": name}))
        deadline = time.monotonic() + args.timeout
        while time.monotonic() < deadline:
            if any(r.ok is not None for r in session.liveliness().get(args.site.raw_key,
                                                                       timeout=0.5)):  # fmt: skip
                print(f"{args.tracker} -> {name}: live on {args.site.raw_key}", file=sys.stderr)
                return 0
            time.sleep(0.1)
    finally:
        session.close()
    print(f"bodynet calibrate assign: no bridge published {args.site.raw_key} within "
          f"{args.timeout:g} s (is the tracker streaming?)", file=sys.stderr)  # fmt: skip
    return 0 if args.profile is not None else 1


class _Unusable(Exception):
    """A capture that gives nothing to write."""


def cmd_process(args: argparse.Namespace) -> int:
    from bodynet.clients.mcap_store import StoreError
    from bodynet.nodes.captures import RECORDING, CaptureError, capture_options, format_of
    from bodynet.offline.process import process

    recording = RECORDING if args.input.suffix.lower() == ".mcap" else None
    fmt = args.format or format_of(args.input) or recording
    if fmt is None:
        from bodynet.nodes.captures import looks_like

        what = looks_like(args.input)
        print("bodynet process: say which --format the capture is in"
              + (f" (it looks like {what})" if what else ""), file=sys.stderr)  # fmt: skip
        return 2
    from bodynet.core.errors import DecodeError
    from bodynet.gateway.heading import CalibrationRefused, dropped_note
    from bodynet.nodes.captures import looks_else
    from bodynet.session.outputs import atomic_path

    calibration = None
    if args.calibration is not None:  # a recording by its suffix, as `calibrate --from`'s
        mcap = RECORDING if args.calibration.suffix.lower() == ".mcap" else None
        calibration = (args.calibration, format_of(args.calibration) or mcap or fmt)
    try:
        profile = with_heading_args(_profile(args.profile), args)
        with atomic_path(args.output, [args.input, args.profile, args.calibration]) as tmp:
            result = process(args.input, fmt, tmp, profile, args.rate_hz,
                             args.tick_hz, args.tpose_s, capture_options(args),
                             calibration, window=args.window, pose=args.pose)  # fmt: skip
            if not result.samples:  # nothing written: no empty recording is left
                raise _Unusable(f"no {fmt} samples in {args.input} ({result.stats.summary()})"
                                + looks_else(args.input, fmt))  # fmt: skip
    except CalibrationRefused as exc:
        print(f"bodynet process: calibration refused: {exc}; nothing written", file=sys.stderr)
        return 1
    except (ProfileError, OSError, CaptureError, DecodeError, StoreError, _Unusable,
            ValueError) as exc:  # fmt: skip
        print(f"bodynet process: {exc}", file=sys.stderr)
        return 2
    heading = result.heading or {}
    note = {
        "found": f"heading found ({heading.get('deg')} deg, {heading.get('hinge')})",
        "declared": f"heading declared ({heading.get('deg')} deg)",
        "fixed": "heading fixed (the subject faced +X)",
        "partly found": "headings found for some tags only (independent tags: the legs' from "
        "a walk, the arms' from a reach, the trunk's from a bow): the other "
        "tags' dofs are flagged uncalibrated",
        "unknown": "heading NOT found (no knee or elbow moved): the tags' dofs are "
        "flagged uncalibrated; bend a knee after the pose, or pass "
        "--heading-reference or --heading fixed",
    }.get(heading.get("state"), "")
    calibrated = (f"calibrated {len(result.calibrated)} sensors ({result.calibration['pose']})"
                  if result.calibration else "calibration from the profile")  # fmt: skip
    if result.refused:
        calibrated = (
            f"NOT calibrated: {result.refused} (the tags' dofs are flagged "
            "uncalibrated; say where the still pose is with --window START:END)"
        )
    dropped = dropped_note(result.calibration) if result.calibration else None
    told = "; ".join(part for part in (calibrated, dropped, note, result.stats.summary())
                     if part)  # fmt: skip
    print(f"{result.ticks} ticks from {result.samples} samples -> {args.output}; {told}",
          file=sys.stderr)  # fmt: skip
    return 0


def add_process_args(p: argparse.ArgumentParser) -> None:
    from bodynet.nodes.captures import RECORDING, add_capture_args, formats

    p.add_argument("input", type=argtypes.input_file,
                   help="a capture (any format of `bodynet decode`), or a recording's raw "
                        "samples (.mcap: solved again, e.g. from another window)")  # fmt: skip
    p.add_argument("--format", choices=[*formats(), RECORDING])
    add_capture_args(p)
    p.add_argument("--rate-hz", type=argtypes.RATE_HZ, default=None,
                   help="as for `bodynet decode`")  # fmt: skip
    p.add_argument("--tick-hz", type=POSE_RATE_HZ, default=100.0,
                   help="most poses per second of capture")  # fmt: skip
    p.add_argument(
        "--tpose-s",
        type=argtypes.non_negative_float(3600.0, "seconds at the capture's start"),
        default=None,
        help="seconds at the start still in the calibration pose, to calibrate orientation "
        "sensors (default 3, or the whole capture if shorter, solved uncalibrated if the "
        "subject moved in them; given, refused as --window is; longer than the capture is "
        "refused; 0: the orientations are the segments' own, as bodynet exports them)",
    )
    p.add_argument("--window", type=argtypes.time_window, default=None, metavar="START:END",
                   help="calibrate from this still window (seconds from the start of the "
                        "capture, or of --calibration) instead; refused if not still")  # fmt: skip
    p.add_argument("--calibration", type=argtypes.input_file,
                   help="take the calibration pose (--tpose-s, --window) from this file of the "
                        "same session, e.g. static.sto (its format from its suffix, else "
                        "--format)")  # fmt: skip
    add_heading_args(p)
    p.add_argument("--profile", type=argtypes.input_file, help="subject profile (TOML)")
    p.add_argument("-o", "--output", type=argtypes.output_file, required=True,
                   help="the MCAP file to write")  # fmt: skip


def _module_site(joint: str) -> tuple[str, str]:
    """The raw key and encoder angle name of a SmartSuit joint like ``left_elbow``."""
    from bodynet.core.profile import OLE_DOF, SMARTSUIT_SITES

    for site in SMARTSUIT_SITES.values():
        if f"{site.branch.side}_{site.name}" == joint and site.name in OLE_DOF:
            return site.raw_key, f"{joint}_{OLE_DOF[site.name]}_deg"
    raise SystemExit(f"bodynet calibrate ole: no SmartSuit encoder at {joint!r}")


def _still_counts(session: object, key: str, seconds: float) -> tuple[float, float, int]:
    """Mean and spread of the encoder over ``seconds`` of live samples of ``key``."""
    import queue
    import statistics
    import time

    import zenoh

    from bodynet.core.codecs import raw_sample
    from bodynet.core.errors import DecodeError
    from bodynet.core.messages import OleAccel

    got: queue.SimpleQueue[int] = queue.SimpleQueue()

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            reading = raw_sample.decode(sample.payload.to_bytes()).reading
        except DecodeError:
            return
        if isinstance(reading, OleAccel):
            got.put(reading.encoder)

    assert isinstance(session, zenoh.Session)
    sub = session.declare_subscriber(key, on_sample)
    values: list[int] = []
    end = time.monotonic() + seconds
    try:
        while (left := end - time.monotonic()) > 0 or not values:
            try:
                values.append(got.get(timeout=max(left, 0.0) + (0.0 if values else 5.0)))
            except queue.Empty:
                if not values:
                    raise SystemExit(f"bodynet calibrate ole: no samples on {key}") from None
                break
    finally:
        sub.undeclare()
    return statistics.fmean(values), statistics.pstdev(values), len(values)


def cmd_calibrate_ole(args: argparse.Namespace) -> int:
    from bodynet.gateway.calibrate import fit_calibration
    from bodynet.session import profile_file

    key, angle_name = _module_site(args.joint)
    try:  # before any pose is held: a profile that cannot be updated is said at once
        profile = _profile(args.profile)
    except ProfileError as exc:
        print(f"bodynet calibrate ole: {exc}; nothing written", file=sys.stderr)
        return 2
    pairs: list[tuple[float, float]] = []
    if args.from_pairs:
        try:
            text = args.from_pairs.read_text(encoding="utf-8-sig", errors="replace")
            pairs = _pairs(text, args.from_pairs)
        except OSError as exc:
            print(f"bodynet calibrate ole: cannot read {args.from_pairs}: {exc.strerror or exc}",
                  file=sys.stderr)  # fmt: skip
            return 2
        except ValueError as exc:
            print(f"bodynet calibrate ole: {exc}; nothing written", file=sys.stderr)
            return 2
    else:
        angles = args.angles
        session = open_session(config_from_args(args))
        try:
            for angle in angles:
                print(f"Hold {args.joint} at {angle:g} deg and keep still, then press Enter",
                      file=sys.stderr, flush=True)  # fmt: skip
                if not sys.stdin.readline():
                    print("bodynet calibrate ole: input ended; nothing written", file=sys.stderr)
                    return 1
                mean, spread, n = _still_counts(session, key, args.still_s)
                print(f"  {angle:g} deg: {mean:.1f} counts (sd {spread:.2f}, {n} samples)",
                      file=sys.stderr)  # fmt: skip
                pairs.append((angle, mean))
        finally:
            session.close()
    if len(pairs) < 2:
        print("bodynet calibrate ole: need at least two (angle, counts) pairs", file=sys.stderr)
        return 2
    try:
        cal, fit = fit_calibration([a for a, _ in pairs], [c for _, c in pairs])
        if not (math.isfinite(fit.radius_mm) and math.isfinite(fit.r)):
            raise ValueError(f"R = {fit.radius_mm} mm, r = {fit.r}")
        profile = profile.with_ole(angle_name, cal)
    except ValueError as exc:  # ProfileError too
        print(f"bodynet calibrate ole: no usable calibration from these pairs ({exc}); "
              "nothing written", file=sys.stderr)  # fmt: skip
        return 2
    try:
        profile_file.save(profile, args.profile)
    except OSError as exc:  # OutputError names the profile
        print(f"bodynet calibrate ole: {exc}", file=sys.stderr)
        return 2
    table = ", ".join(f"{d:g} mm: {s:.3f}" for d, s in zip(cal.sf_d_mm, cal.sf, strict=True))
    print(
        f"{angle_name}: R = {cal.radius_mm:.2f} mm (eq. 26 over all poses: "
        f"{fit.radius_mm:.2f} mm, r = {fit.r:.4f}); SF: {table}; saved to {args.profile}"
    )
    return 0


def _pairs(text: str, path: Path) -> list[tuple[float, float]]:
    """The ``angle_deg,counts`` rows of a ``--from-pairs`` file (``;`` as well as
    ``,``; blank lines and a first line that is no numbers, a header, skipped):
    each row two finite numbers, the angle within +-360 deg as ``--angles``'
    (``ValueError`` naming the file and line of the first that is not)."""
    pairs: list[tuple[float, float]] = []
    first = True
    for number, line in enumerate(text.splitlines(), start=1):
        fields = [f.strip() for f in line.replace(";", ",").split(",")]
        if not any(fields):
            continue
        try:
            pair: tuple[float, float] | None = (float(fields[0]), float(fields[1]))
        except (ValueError, IndexError):
            if first and not _number(fields[0]):
                first = False
                continue  # the header
            pair = None
        first = False
        if pair is None or len(fields) != 2 or not math.isfinite(pair[1]):
            raise ValueError(f"{path}: line {number}: not angle_deg,counts (two finite "
                             f"numbers): {line.strip()[:60]!r}")  # fmt: skip
        if not abs(pair[0]) <= 360.0:  # NaN too
            raise ValueError(f"{path}: line {number}: angle {fields[0][:20]} is not within "
                             "+-360 deg")  # fmt: skip
        pairs.append(pair)
    return pairs


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _ole_joints() -> list[str]:
    from bodynet.core.profile import OLE_DOF, SMARTSUIT_SITES

    return sorted(f"{s.branch.side}_{s.name}" for s in SMARTSUIT_SITES.values()
                  if s.name in OLE_DOF)  # fmt: skip


def _angles(text: str) -> list[float]:
    """``0,30,60`` -> [0.0, 30.0, 60.0]: finite angles within +-360 deg."""
    check = argtypes.bounded_float(-360.0, 360.0, "degrees")
    try:
        return [check(a) for a in text.split(",")]
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{text!r} is not a list of angles: {exc}") from None


def add_calibrate_ole_parser(csub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = csub.add_parser("ole", help="an encoder's radius and scale factors from reference poses")
    p.add_argument("--joint", required=True, choices=_ole_joints(), metavar="JOINT",
                   help="e.g. left_elbow, right_knee")  # fmt: skip
    p.add_argument("--angles", default="0,30,60,90,120,140", type=_angles,
                   help="reference angles to hold (deg)")  # fmt: skip
    p.add_argument("--from-pairs", type=argtypes.input_file,
                   help="CSV of angle_deg,counts instead of live poses")  # fmt: skip
    p.add_argument("--still-s", type=argtypes.bounded_float(0.1, 60.0, "seconds"), default=1.0,
                   help="still window to average per pose")  # fmt: skip
    p.add_argument("--profile", type=argtypes.input_or_new_file, required=True,
                   help="profile to update (or create)")  # fmt: skip
    add_session_args(p)
    p.set_defaults(func=cmd_calibrate_ole)
