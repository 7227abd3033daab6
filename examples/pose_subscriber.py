"""Print the elbows' angles from every whole-body pose the gateway publishes.

make demo                                        # in another terminal, or any gateway
.venv/bin/python examples/pose_subscriber.py     # -e tcp/HOST:7447 for a remote router
"""

import argparse

import zenoh

from bodynet.core import keys
from bodynet.core.codecs import pose
from bodynet.session import add_session_args, config_from_args, open_session


def main(conf: zenoh.Config, count: int) -> None:
    with open_session(conf) as session, session.declare_subscriber(keys.pose_key()) as sub:
        for n, sample in enumerate(sub, start=1):
            frame = pose.decode(sample.payload.to_bytes())
            elbows = {k: round(v, 1) for k, v in frame.angles_deg.items() if "elbow" in k}
            print(frame.seq, elbows, flush=True)
            if n == count:
                break


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_session_args(parser)  # --mode, -e/--connect, -l/--listen, -c/--config, --cfg, --subject
    parser.add_argument("--count", type=int, default=0, help="stop after N poses (default: never)")
    args = parser.parse_args()
    main(config_from_args(args), args.count)
