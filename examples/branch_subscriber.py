"""Subscribe to one branch only, e.g. from a clinic across the network.

The router sends this process the branch's pose view (``body/arm/left/pose``)
and nothing else of the body:

    .venv/bin/python examples/branch_subscriber.py -e tcp/clinic-router.local:7447 --branch left-arm
"""

import argparse

import zenoh

from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.session import add_session_args, config_from_args, open_session


def main(conf: zenoh.Config, branch: keys.Branch, count: int) -> None:
    with open_session(conf) as session, session.declare_subscriber(keys.pose_key(branch)) as sub:
        for n, sample in enumerate(sub, start=1):
            frame = pose.decode(sample.payload.to_bytes())
            print(sample.key_expr, frame.seq, sorted(frame.segments), f"stale={list(frame.stale)}",
                  flush=True)  # fmt: skip
            if n == count:
                break


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_session_args(parser)
    parser.add_argument("--branch", default="left-arm", choices=[str(b) for b in keys.BRANCHES])
    parser.add_argument("--count", type=int, default=0, help="stop after N poses (default: never)")
    args = parser.parse_args()
    main(config_from_args(args), keys.branch_named(args.branch), args.count)
