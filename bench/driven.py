"""The gateway worker's rounds driven with explicit clocks, no network (docs/benchmarks.md).

``python bench/driven.py FEED HOLD`` with FEED ``locked`` (every node at once) or
``phased`` (each body and node at its own phase), HOLD 1 (the worker counts as
busy: whole frames wait for the round) or 0; ``NB`` bodies (environment, default
4; body 1 loses a site after 1 s). Prints the worker thread's CPU per body-tick
(solve, pose message, encode; after the first 0.2 s), the bodies per solve, and a
hash of every pose message (whole body and branch views, per key in order).
Run it with each version's interpreter to compare them (a version without
``Gateway._round`` is driven by a copy of its loop, ``base_round``);
``ORACLE_DUMP=file`` pickles the messages."""

import hashlib
import os
import pickle
import sys
import time

import numpy as np

from bodynet.core.messages import RawSample, Source
from bodynet.gateway.service import Gateway
from bodynet.nodes.emulator import BodyEmulator, imu_tags
from bodynet.nodes.motion import ROUTINES
from bodynet.session import open_session, session_config


class Pub:
    def __init__(self, key, out):
        self.key, self.out = key, out

    def put(self, payload):
        self.out.append((self.key, bytes(payload)))


def main():  # noqa: PLR0915 (a measurement script, read top to bottom)
    feed, hold = sys.argv[1], sys.argv[2] == "1"
    conf = session_config("peer")
    conf.insert_json5("scouting/multicast/enabled", "false")
    s = open_session(conf)
    gw = Gateway(s, all_subjects=True)
    if hold and hasattr(gw, "rounds"):
        from bodynet.gateway.rounds import Rounds

        gw.rounds = Rounds(0.01, busy_on=0.0, busy_off=0.0)
    elif hasattr(gw, "rounds"):
        from bodynet.gateway.rounds import Rounds

        gw.rounds = Rounds(0.01, busy_on=2.0)
    out = []
    tags = imu_tags()
    NB = int(os.environ.get("NB", "4"))
    emus = [BodyEmulator(ROUTINES["walk"], tags, seed=b) for b in range(NB)]
    bodies = [gw._body(f"s{b}") for b in range(NB)]
    for b, body in enumerate(bodies):
        body.body_pub = Pub(f"s{b}/body", out)
        body.branch_pubs = {br: Pub(f"s{b}/{br.key}", out) for br in body.branch_pubs}
        body.listened = lambda body=body: (True, [])  # the whole body only, as the bench probe
    P, STEP, seconds = 0.01, 0.00025, 2.0
    rng = np.random.default_rng(5)
    if feed == "locked":
        phases = np.zeros((NB, 15))
    else:
        phases = rng.uniform(0, P, (NB, 1)) + rng.uniform(0, P, (NB, 15))
    sent = np.zeros((NB, 15), dtype=int)
    cpu = 0.0
    for step in range(1, int(seconds / STEP) + 1):
        now = step * STEP
        touched = set()
        for b, body in enumerate(bodies):
            for i, tag in enumerate(tags):
                if b == 1 and i == 3 and now > 1.0:
                    continue  # a site drops out
                while phases[b, i] + sent[b, i] * P <= now + 1e-12:
                    t = phases[b, i] + sent[b, i] * P
                    reading = emus[b].sample(t)[0][i]
                    body.take(
                        tag.site,
                        RawSample(reading, int(sent[b, i]), round(t * 1e9), Source.IMU_CENTRAL),
                        now,
                    )
                    sent[b, i] += 1
                    touched.add(body)
        c0 = time.thread_time()
        if hasattr(gw, "_round"):
            gw._round(now, touched)
        else:
            base_round(gw, now, touched)
        if now > 0.2:
            cpu += time.thread_time() - c0

    with open(os.environ.get("ORACLE_DUMP", "/dev/null"), "wb") as dump:
        pickle.dump(out, dump)
    h = hashlib.sha256()
    # per key in publishing order (the order of bodies within one batch follows a set's)
    for k, p in sorted(out, key=lambda kp: kp[0]):
        h.update(k.encode())
        h.update(p)
    ticks = sum(b.ticks for b in bodies)
    print(
        f"CPU {cpu / ticks * 1e6:.0f} us per body-tick (after 0.2 s), "
        f"{ticks / max(1, getattr(gw, 'solves', 1)):.1f} bodies per solve"
    )
    sys.stdout.flush()
    print(
        feed,
        "hold" if hold else "at-once",
        len(out),
        "messages",
        [b.ticks for b in bodies],
        "ticks",
        h.hexdigest()[:16],
    )
    s.close()


def base_round(gw, now, touched):
    """main's run() loop body, as it was (541dc07), without the take and the sleep."""
    due = {}
    nd = getattr(gw, "_nd", float("inf"))
    with gw._lock:
        for body in touched:
            if body.frame_complete(now):
                due[body] = False
            elif body.first_new is not None:
                nd = min(nd, body.first_new + gw.period_s)
    if now >= nd:
        for body in list(gw._bodies.values()):
            if body.first_new is not None and now - body.first_new >= gw.period_s:
                due.setdefault(body, False)
        firsts = [
            b.first_new for b in gw._bodies.values() if b.first_new is not None and b not in due
        ]
        nd = min(firsts, default=float("inf")) + gw.period_s
    gw._nd = nd
    gw._solve_and_publish(due, now)
    gw._housekeeping(now)


if __name__ == "__main__":
    main()
