"""The key space: every Zenoh key expression bodynet uses is built here.

Raw samples live at ``body/<limb>/<side>/<site>/raw``. The ``<limb>/<side>``
pair is a *branch* of the SmartSuit distributed bus (000 seed, ch. 3.1.7):
left arm, right arm, left leg, right leg and trunk-head, so ``body/arm/left/**``
selects one branch. Sites name where a sensor sits: SmartSuit modules by the
joint their encoder spans (``shoulder``, ``elbow``...), IMU tags of the 003 seed
(Table 5.2) by the segment they ride on (``upperarm``, ``forearm``...), so the
two systems can share one body without their keys colliding.

Several subjects share one network through Zenoh namespaces: a process
started with ``--subject alice`` sees and writes ``body/...`` while the wire
carries ``alice/body/...``. A process without a namespace (a gateway serving
every subject, a listing of the subjects present) uses ``subject_prefix`` and
``split_subject``.

Nothing else in the code base writes a key as a string literal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from functools import lru_cache

ROOT = "body"


class Limb(StrEnum):
    """The first key level below ``body``: which part of the body network."""

    ARM = "arm"
    LEG = "leg"
    TRUNK = "trunk"


class Side(StrEnum):
    LEFT = "left"
    RIGHT = "right"
    MID = "mid"


class Stream(StrEnum):
    """The last key level: what a key carries about its site."""

    RAW = "raw"
    TRUTH = "truth"  # an emulator's ground truth for the site


class KeySpaceError(ValueError):
    """A key expression that is not part of the bodynet key space."""


@dataclass(frozen=True, slots=True, order=True)
class Branch:
    """One branch of the body bus, such as the left arm."""

    limb: Limb
    side: Side
    # computed once (an enum's hash is Python code): branches and sites key the
    # dictionaries on every sample's path
    _hash: int = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if (self.limb is Limb.TRUNK) != (self.side is Side.MID):
            raise KeySpaceError(f"no branch {self.limb}/{self.side}: only the trunk is 'mid'")
        object.__setattr__(self, "_hash", hash((self.limb, self.side)))

    def __hash__(self) -> int:
        return self._hash

    def __reduce__(self) -> tuple[type[Branch], tuple[Limb, Side]]:
        return Branch, (self.limb, self.side)  # the hash is this process's: not pickled

    @property
    def key(self) -> str:
        return f"{ROOT}/{self.limb}/{self.side}"

    @property
    def selector(self) -> str:
        """Key expression matching everything published on this branch."""
        return f"{self.key}/**"

    def __str__(self) -> str:
        return f"{self.side}-{self.limb}" if self.side is not Side.MID else str(self.limb)


LEFT_ARM = Branch(Limb.ARM, Side.LEFT)
RIGHT_ARM = Branch(Limb.ARM, Side.RIGHT)
LEFT_LEG = Branch(Limb.LEG, Side.LEFT)
RIGHT_LEG = Branch(Limb.LEG, Side.RIGHT)
TRUNK = Branch(Limb.TRUNK, Side.MID)

#: The five branches of the distributed bus, in the seed's node order.
BRANCHES: tuple[Branch, ...] = (LEFT_ARM, RIGHT_ARM, LEFT_LEG, RIGHT_LEG, TRUNK)


def branch_named(name: str) -> Branch:
    """The branch called ``name`` (``left-arm``, ``right-leg``, ``trunk``...)."""
    for branch in BRANCHES:
        if str(branch) == name:
            return branch
    raise KeySpaceError(f"no branch {name!r}; branches: {', '.join(map(str, BRANCHES))}")


#: Site names each limb may carry. SmartSuit modules first, then IMU segments.
SITES: dict[Limb, tuple[str, ...]] = {
    Limb.ARM: ("shoulder", "elbow", "wrist", "upperarm", "forearm", "hand"),
    Limb.LEG: ("hip", "knee", "ankle", "thigh", "shank", "foot"),
    Limb.TRUNK: ("head", "upper_trunk", "lower_trunk", "forehead", "chest", "sacrum"),
}


@dataclass(frozen=True, slots=True, order=True)
class Site:
    """A sensor site: one branch plus a site name, e.g. the left elbow."""

    branch: Branch
    name: str
    _hash: int = field(init=False, repr=False, compare=False)  # as Branch's
    _raw_key: str = field(init=False, repr=False, compare=False)  # asked every tick

    def __post_init__(self) -> None:
        if self.name not in SITES[self.branch.limb]:
            raise KeySpaceError(f"site {self.name!r} is not on limb {self.branch.limb}")
        object.__setattr__(self, "_hash", hash((self.branch, self.name)))
        object.__setattr__(self, "_raw_key", self.key(Stream.RAW))

    def __hash__(self) -> int:
        return self._hash

    def __reduce__(self) -> tuple[type[Site], tuple[Branch, str]]:
        return Site, (self.branch, self.name)  # the hash is this process's: not pickled

    def key(self, stream: Stream = Stream.RAW) -> str:
        return f"{self.branch.key}/{self.name}/{stream}"

    @property
    def raw_key(self) -> str:
        return self._raw_key

    def __str__(self) -> str:
        return f"{self.branch.side}/{self.branch.limb}/{self.name}"


def raw_key(limb: Limb | str, side: Side | str, site: str) -> str:
    """Key of the raw samples of one site: ``raw_key("arm", "left", "elbow")``."""
    return Site(Branch(Limb(limb), Side(side)), site).raw_key


def all_raw() -> str:
    """Key expression matching every raw sample of a body."""
    return f"{ROOT}/*/*/*/{Stream.RAW}"


def all_truth() -> str:
    """Key expression matching every emulator's ground truth."""
    return f"{ROOT}/*/*/*/{Stream.TRUTH}"


POSE = "pose"


def pose_key(branch: Branch | None = None) -> str:
    """Where the gateway publishes poses: the whole body, or one branch's view."""
    return f"{ROOT}/{POSE}" if branch is None else f"{branch.key}/{POSE}"


def all_poses() -> str:
    """Every pose message of a body: the whole body and each branch view."""
    return f"{ROOT}/**/{POSE}"


#: MCAP topic of the segment transforms derived from ``body/pose`` (Foxglove's
#: ``foxglove.FrameTransforms``). Written into recordings only, never published.
TRANSFORMS = f"{ROOT}/tf"


#: Admin keys start with a verbatim chunk (``@...``), which Zenoh wildcards never
#: match: ``body/**`` gets data only, and admin traffic is asked for by name.
HEALTH = f"{ROOT}/@health"


TOPOLOGY = f"{ROOT}/@topology"
#: Per subject, about twice a second: each observed dof's range of motion so far,
#: repetitions and the smoothness of its current movement (``core/metrics.py``).
METRICS = f"{ROOT}/@metrics"
CALIBRATE_TPOSE = f"{ROOT}/@calibrate/tpose"
#: The yaw reset: the subject faces forward now (a query; the gateway answers).
CALIBRATE_YAW = f"{ROOT}/@calibrate/yaw"
#: Liveliness tokens of sensors a bridge sees but no site is assigned to yet:
#: ``body/@unassigned/<tracker id>`` (the gateway lists them in the topology).
UNASSIGNED = f"{ROOT}/@unassigned"
#: ``bodynet calibrate assign`` puts ``{"tracker": id, "site": "left-arm/upperarm"}``
#: here; bridges that serve the tracker take it at once.
ASSIGN = f"{ROOT}/@assign"


#: ``body/@batch/<bridge>``: a bridge's samples of a few ms in one message
#: (``codecs.raw_batch``; a bridge run with ``--batch-ms``).
BATCH = f"{ROOT}/@batch"


def batch_key(source: str) -> str:
    """Key of one bridge's batches of raw samples, e.g. ``body/@batch/imu-ttyUSB0``."""
    return f"{BATCH}/{chunk(source)}"


def all_batches() -> str:
    """Key expression matching every bridge's batches of a body."""
    return f"{BATCH}/*"


def unassigned_key(tracker: str) -> str:
    return f"{UNASSIGNED}/{chunk(tracker)}"


def site_named(text: str) -> Site:
    """The site a user names ``left-arm/upperarm`` (branch name / site name)."""
    branch_text, sep, name = text.strip().rpartition("/")
    if not sep:
        raise KeySpaceError(f"not a site like left-arm/upperarm: {text!r}")
    return Site(branch_named(branch_text), name)


def site_name(site: Site) -> str:
    """``left-arm/upperarm``: how :func:`site_named` reads it."""
    return f"{site.branch}/{site.name}"


def health_key(source: str) -> str:
    """Admin key of one bridge's health, e.g. ``body/@health/can-vcan0``."""
    return f"{HEALTH}/{chunk(source)}"


def chunk(text: str) -> str:
    """``text`` made safe as one key chunk (no ``/ * $ ? # @`` or spaces)."""
    safe = "".join(c if c.isalnum() or c in "-_." else "-" for c in text).strip("-")
    return safe or "unnamed"


@lru_cache(maxsize=4096)  # on every sample's path; the key space is small
def parse(key: str) -> tuple[Site, Stream]:
    """Split a concrete key into its site and stream; raise ``KeySpaceError`` if foreign."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != ROOT:
        raise KeySpaceError(f"not a bodynet site key: {key!r}")
    try:
        site = Site(Branch(Limb(parts[1]), Side(parts[2])), parts[3])
        return site, Stream(parts[4])
    except ValueError as exc:
        raise KeySpaceError(f"not a bodynet site key: {key!r} ({exc})") from None


#: Every subject's namespace, as the first chunk of a key expression.
ANY_SUBJECT = "*"

#: Liveliness tokens of the gateways sharing the subjects (``gateway --share``):
#: outside every subject's namespace, verbatim so that no wildcard matches it.
GATEWAYS = "@bodynet/gateways"


def gateway_token(gateway_id: str) -> str:
    """The liveliness token of one sharing gateway."""
    return f"{GATEWAYS}/{gateway_id}"


def subject_name(name: str) -> str:
    """``name`` if it can be a subject namespace (one key chunk, not ``body``)."""
    if not name or name == ROOT or chunk(name) != name:
        raise KeySpaceError(
            f"subject {name!r} must be one key chunk of letters, digits, '-', '_' or '.', "
            f"and not {ROOT!r}"
        )
    return name


def subject_prefix(subject: str | None) -> str:
    """What a namespace-less session puts before ``body/...`` for ``subject``."""
    return "" if subject is None else f"{subject}/"


@lru_cache(maxsize=4096)
def split_subject(key: str) -> tuple[str | None, str]:
    """``("alice", "body/...")`` for ``alice/body/...``; ``(None, key)`` for ``body/...``."""
    if key.startswith(ROOT + "/"):
        return None, key
    subject, sep, rest = key.partition("/")
    if not sep or not rest.startswith(ROOT + "/"):
        raise KeySpaceError(f"not a bodynet key: {key!r}")
    return subject, rest


def all_sites(stream: Stream) -> str:
    """Key expression matching one stream of every site of a body, e.g. all truths."""
    return f"{ROOT}/*/*/*/{stream}"


def all_data() -> str:
    """Every data key of a body (raw samples, truths, poses); never the ``@`` admin keys."""
    return f"{ROOT}/**"


def all_health() -> str:
    """Every health key of a body: the bridges' and the gateway's."""
    return f"{HEALTH}/**"
