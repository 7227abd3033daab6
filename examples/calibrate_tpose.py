"""Ask the gateway to calibrate the IMU mounts: the subject stands still in T-pose.

A Zenoh query on ``body/@calibrate/tpose``; the gateway answers with a JSON
verdict (``ok``, the sensors it calibrated, or why it refused):

    .venv/bin/python examples/calibrate_tpose.py --seconds 1
"""

import argparse
import json
import sys

import zenoh

from bodynet.core import keys
from bodynet.session import add_session_args, config_from_args, open_session


def main(conf: zenoh.Config, seconds: float) -> bool:
    with open_session(conf) as session:
        for reply in session.get(f"{keys.CALIBRATE_TPOSE}?seconds={seconds}", timeout=10.0):
            if reply.ok is not None:
                verdict = json.loads(reply.ok.payload.to_bytes())
                print(json.dumps(verdict, indent=2))
                return bool(verdict.get("ok"))
    print("no gateway answered", file=sys.stderr)
    return False


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    add_session_args(parser)
    parser.add_argument("--seconds", type=float, default=1.0, help="still window to average")
    args = parser.parse_args()
    sys.exit(0 if main(config_from_args(args), args.seconds) else 1)
