"""The gateway's whole-body message, encoded straight from the solver's arrays
(``whole_body_message``), is byte for byte the message of the pose frame
(``pose.encode(pose_frame(...))``), which offline processing and the branch
views still build: for bodies of every kind, calibrated or not, with flags,
uncertainties of null, clamped dofs and stale sites. Its numbers are written
by a compiled writer (``kernels.write_message``), held here to orjson's text
of the same rounded floats over some 760,000 numbers, and handing what it does
not write back to orjson."""

from __future__ import annotations

import math

import numpy as np
import orjson
import pytest

from bodynet.core.codecs import pose
from bodynet.core.keys import LEFT_ARM
from bodynet.core.messages import RawSample, Source
from bodynet.core.subject import Profile
from bodynet.gateway import kernels
from bodynet.gateway.frames import pose_frame, whole_body_message
from bodynet.gateway.solver import BodyOutput, BodySolver, solve_bodies
from bodynet.nodes.emulator import BodyEmulator, Realism, imu_tags, smartsuit_sensors
from bodynet.nodes.motion import ROUTINES
from tests.test_gateway_solver import IDEAL_RANDOM_MOUNTS, calibrated_profile


def test_whole_body_messages_are_the_frames_messages() -> None:
    tags = imu_tags()
    hybrid = [t for t in tags if t.site.name in ("upperarm", "chest", "sacrum")]
    hybrid += [s for s in smartsuit_sensors([LEFT_ARM]) if s.site.name != "shoulder"]
    kinds = [  # sensors, profile, routine, realism
        (tags, calibrated_profile(tags), "walk", IDEAL_RANDOM_MOUNTS),
        (tags, Profile(), "reach", None),  # uncalibrated: flags and reasons on most dofs
        (smartsuit_sensors(), Profile(), "reach", None),
        (hybrid, calibrated_profile([t for t in tags if t in hybrid]), "full-body",
         IDEAL_RANDOM_MOUNTS),
    ]  # fmt: skip
    bodies = [
        (BodySolver(profile),
         BodyEmulator(ROUTINES[routine], sensors, realism=realism or Realism.ideal(), seed=1))
        for sensors, profile, routine, realism in kinds
    ]  # fmt: skip
    checked, flagged, nulls = 0, 0, 0
    for k in range(150):
        t = k * 0.04
        work = []
        for solver, body in bodies:
            readings, _ = body.sample(t)
            latest = {s.site: RawSample(r, k, round(t * 1e9), Source.CAN)
                      for s, r in zip(body.sensors, readings, strict=True)
                      if not (k > 60 and s.site.name == "forearm")}  # fmt: skip
            work.append((solver, latest))
        for b, output in enumerate(solve_bodies(work)):
            stale = ["body/arm/left/forearm/raw"] if k > 60 and b % 2 else []
            expected = pose.encode(pose_frame(output, k, stale))
            assert whole_body_message(output, k, stale) == expected, (k, b)
            checked += 1
            flagged += bool(output.flags)
            nulls += int(np.isnan(output.unc).sum())
    # what the comparison covered
    assert checked == 600
    assert flagged > 150
    assert nulls > 0
    # a number past what the compiled writer spells goes to orjson: the same bytes
    output = solve_bodies(work)[0]
    output.rel[0] = 1e16
    assert _compiled(output, 7, []) == kernels.REFUSED
    assert whole_body_message(output, 7, []) == pose.encode(pose_frame(output, 7, []))
    assert b"1e+16" in whole_body_message(output, 7, [])


def _compiled(output: BodyOutput, seq: int, stale: list[str]) -> int:
    """What ``kernels.write_message`` returns for an output (its length, or why not)."""
    encoder = output.names.encoder
    parts = (output.positions.ravel(), output.quats.ravel(), output.angles, output.rel, output.unc)
    maps = [orjson.dumps(m) for m in (output.flags, output.sources, stale, output.reasons)]
    out = np.empty(encoder.capacity + sum(map(len, maps)), dtype=np.uint8)
    return int(kernels.write_message(np.concatenate(parts), encoder.order, encoder.scale,
                                     encoder.places, encoder.text, encoder.ends, encoder.slots,
                                     seq, output.t_ns, *maps, out))  # fmt: skip


def test_the_compiled_writer_spells_numbers_as_orjson() -> None:
    """Some 760,000 numbers, rounded to six places (angles) and three
    (uncertainties), through the compiled writer and through orjson: the same
    text. Every integer count of the last place near zero, where the text
    changes form (``1e-6``, ``0.00001``, ``-0.0``), halves (rounded to even),
    and numbers of every size up to ``ROUNDED_MAX`` units."""
    rng = np.random.default_rng(11)
    near = np.arange(-20_000, 20_001)
    wide = rng.integers(-(10**15) + 1, 10**15, 100_000)
    for places in (6, 3):
        unit = 10.0**-places
        jittered = wide + rng.uniform(-0.5, 0.5, wide.size)
        values = np.concatenate([
            near * unit, (near + 0.5) * unit, wide * unit, jittered * unit,
            rng.normal(size=100_000) * 10.0 ** rng.integers(-9, 15 - places, 100_000),
            [math.nan, math.inf, -math.inf, -0.0, 0.0, -1e-9, 4e-7, -6e-7, 0.5e-6, 2.5e-6],
        ])  # fmt: skip
        # what the writer hands back to orjson aside (NaN and the infinities kept: null)
        with np.errstate(invalid="ignore"):
            written = np.abs(np.rint(values / unit)) < kernels.ROUNDED_MAX
        values = values[written | ~np.isfinite(values)]
        assert np.isinf(values).sum() == 2
        names = [f"a{i}" for i in range(len(values))]
        encoder = pose.WholeBodyEncoder(names, (), (), ())
        # the angles are rounded to six places, their uncertainties to three: the
        # numbers under test go where they are rounded as ``places`` says
        numbers = np.concatenate([values, values]) if places == 6 else \
            np.concatenate([np.zeros(len(values)), values])  # fmt: skip
        maps = [orjson.dumps(m) for m in ({}, {}, [], {})]
        out = np.empty(encoder.capacity, dtype=np.uint8)
        n = kernels.write_message(numbers, encoder.order, encoder.scale, encoder.places,
                                  encoder.text, encoder.ends, encoder.slots, 3, 17, *maps,
                                  out)  # fmt: skip
        assert n > 0
        assert out[:n].tobytes() == encoder.encode(3, 17, numbers, {}, {}, [], {}), places
    big = pose.WholeBodyEncoder(["a"], (), (), ())
    out = np.empty(big.capacity, dtype=np.uint8)
    for number in (1e9, -1e9):  # 1e15 units of 1e-6
        got = kernels.write_message(np.array([number, 0.0]), big.order, big.scale, big.places,
                                    big.text, big.ends, big.slots, 0, 0, b"{}", b"{}", b"[]",
                                    b"{}", out)  # fmt: skip
        assert got == kernels.REFUSED


def test_names_are_escaped_and_numbers_written_as_the_frame_does() -> None:
    """Names that JSON or %-formatting would trip on, and numbers at the edges
    of the rounding: NaN, negative zero, tiny and huge values."""
    angles = ('a"1_deg', "b%s_deg", "c\\d_deg")
    joints, segments = ("j%d", "k"), ("s0", "s%%1")
    rng = np.random.default_rng(3)
    positions = rng.normal(size=(2, 3)) * [1e-7, 1e3, 1.0]
    quats = np.array([[1.0, -0.0, 4e-7, -6e-7], [0.5, 0.5, 0.5, 0.5]])
    angle_values = np.array([math.nan, -1e-9, 123456.7891234])
    rel = np.array([1e16, -2.5e-6])
    unc = np.array([0.0004999, math.nan, 7.0])
    encoder = pose.WholeBodyEncoder(angles, joints, segments, (1, 0))
    numbers = np.concatenate([positions.ravel(), quats.ravel(), angle_values, rel, unc])
    flags = {'a"1_deg': "held"}
    reasons = {'a"1_deg': ["uncalibrated", "held"]}
    sources = {"body/x/raw": 17}
    got = encoder.encode(9, 1700000000000000001, numbers, flags, sources, ["body/y/raw"], reasons)

    def r6(v: np.ndarray) -> list[float]:
        return np.round(v, 6).tolist()  # type: ignore[no-any-return]

    p, q = r6(positions), r6(quats)
    frame = pose.PoseFrame(
        9, 1700000000000000001,
        dict(zip(angles, r6(angle_values), strict=True)), dict(zip(joints, r6(rel), strict=True)),
        {s: (tuple(p[i]), tuple(q[i])) for i, s in enumerate(segments)},  # type: ignore[misc]
        {"j%d": tuple(p[1]), "k": tuple(p[0])},  # type: ignore[dict-item]
        flags, sources, ["body/y/raw"], reasons,
        dict(zip(angles, np.round(unc, 3).tolist(), strict=True)),
    )  # fmt: skip
    assert got == pose.encode(frame)
    assert orjson.loads(got)["unc_deg"]["b%s_deg"] is None
    with pytest.raises(ValueError, match="numbers"):
        encoder.encode(9, 1, numbers[:-1], {}, {}, [], {})
