from __future__ import annotations

import pytest

from bodynet.core import keys
from bodynet.core.keys import LEFT_ARM, TRUNK, Branch, KeySpaceError, Limb, Side, Site
from bodynet.core.profile import IMU_SENSORS, IMU_SITES, SMARTSUIT_SITES


def test_design_example_key_exactly() -> None:
    assert keys.raw_key("arm", "left", "elbow") == "body/arm/left/elbow/raw"
    assert SMARTSUIT_SITES[2].raw_key == "body/arm/left/elbow/raw"


def test_branch_selector_selects_one_branch() -> None:
    assert LEFT_ARM.selector == "body/arm/left/**"
    assert [str(b) for b in keys.BRANCHES] == [
        "left-arm", "right-arm", "left-leg", "right-leg", "trunk",
    ]  # fmt: skip


def test_default_profile_smartsuit_nodes() -> None:
    names = [(s.branch.limb, s.branch.side, s.name) for s in SMARTSUIT_SITES.values()]
    assert names[:3] == [("arm", "left", n) for n in ("shoulder", "elbow", "wrist")]
    assert names[3:6] == [("arm", "right", n) for n in ("shoulder", "elbow", "wrist")]
    assert names[6:9] == [("leg", "left", n) for n in ("hip", "knee", "ankle")]
    assert names[9:12] == [("leg", "right", n) for n in ("hip", "knee", "ankle")]
    assert all(s.branch == TRUNK for s in list(SMARTSUIT_SITES.values())[12:])


def test_imu_sites_follow_table_5_2() -> None:
    assert len(IMU_SITES) == 15
    assert IMU_SENSORS[1][0] == "Forehead"
    assert IMU_SITES[3].raw_key == "body/arm/left/upperarm/raw"  # "Left Arm": upper arm
    assert IMU_SITES[6].raw_key == "body/arm/right/forearm/raw"  # "Right Wrist": forearm
    assert IMU_SITES[10].raw_key == "body/leg/left/thigh/raw"  # "Left Knee": thigh
    assert IMU_SITES[13].raw_key == "body/leg/right/shank/raw"  # "Right Ankle": shank
    assert IMU_SITES[9].raw_key == "body/trunk/mid/sacrum/raw"


def test_every_key_unique_and_parses_back() -> None:
    sites = list(SMARTSUIT_SITES.values()) + list(IMU_SITES.values())
    assert len({s.raw_key for s in sites}) == 30
    for site in sites:
        assert keys.parse(site.raw_key) == (site, keys.Stream.RAW)


@pytest.mark.parametrize(
    "key",
    ["body/arm/left/elbow", "body/arm/mid/elbow/raw", "body/trunk/left/head/raw",
     "body/arm/left/knee/raw", "other/arm/left/elbow/raw", "body/arm/left/elbow/cooked"],
)  # fmt: skip
def test_foreign_keys_rejected(key: str) -> None:
    with pytest.raises(KeySpaceError):
        keys.parse(key)


def test_branch_and_site_validation() -> None:
    with pytest.raises(KeySpaceError):
        Branch(Limb.TRUNK, Side.LEFT)
    with pytest.raises(KeySpaceError):
        Site(LEFT_ARM, "hip")


def test_subject_names_and_split() -> None:
    assert keys.subject_name("alice") == "alice"
    for bad in ("", "body", "a/b", "a*", "@x", "a b"):
        with pytest.raises(keys.KeySpaceError):
            keys.subject_name(bad)
    assert keys.split_subject("alice/body/arm/left/elbow/raw") == (
        "alice",
        "body/arm/left/elbow/raw",
    )
    assert keys.split_subject("body/pose") == (None, "body/pose")
    assert keys.subject_prefix("bob") + keys.pose_key() == "bob/body/pose"
    with pytest.raises(keys.KeySpaceError):
        keys.split_subject("alice/other/x")


def test_sites_keep_their_dictionary_identity_across_processes() -> None:
    """A site's hash is computed once per process (it keys the hot path's
    dictionaries); one pickled in a process of another hash seed still finds
    its entry here, and equal sites hash alike."""
    import os
    import pickle
    import subprocess
    import sys

    made_there = subprocess.run(
        [sys.executable, "-c", "import pickle, sys; from bodynet.core import keys; "
         "sys.stdout.buffer.write(pickle.dumps({keys.parse('body/arm/left/elbow/raw')[0]: 1}))"],
        env={**os.environ, "PYTHONHASHSEED": "1"}, capture_output=True, check=True,
    ).stdout  # fmt: skip
    here = keys.Site(keys.Branch(keys.Limb.ARM, keys.Side.LEFT), "elbow")
    assert pickle.loads(made_there)[here] == 1
    assert hash(here) == hash(keys.parse("body/arm/left/elbow/raw")[0])
    assert {keys.LEFT_ARM: 1}[keys.Branch(keys.Limb.ARM, keys.Side.LEFT)] == 1
    assert here != keys.Site(keys.LEFT_ARM, "wrist")
