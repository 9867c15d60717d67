"""The solve's foot contacts against the motion capture's, on the CMU test split's flat-ground walk and runs.

    .venv/bin/python bench/sparse_contacts.py [--weights PATH] [--raise-cm 2] [--max-seconds 60]

Each take (held-out subjects, MC: hands always seen) is tracked as a headset stream by
SparseTracker (shipped weights unless --weights; the body sized from the eye height, the floor
given at the capture's ground), the network's body optionally raised by --raise-cm (a network
whose feet float higher), then solved one frame at a time (as SparseTracker.update runs it) with the fixed-height contact rule
(relative_contact=False, the solve before issue 27's third pass) and with today's rule. Printed
per rule: precision and recall of the solve's planted foot-frames against the truth's contacts
(humotion.sparse.solve.foot_contacts on the motion capture, the metrics' rule: sole under 6 cm,
ball under 0.3 m/s); "skate @truth", the solved balls' mean horizontal speed over the truth's
contact frames (cm/s); the bench's own skating and contact count (metrics.skating over the
solved output's contacts by the metrics' rule, as bench/sparse_eval.py reports them) and
penetration (percent of frames a sole is over 2 cm below the floor, deepest cm). Also the
network's ball speed on the truth's contact frames (its median and 90th percentile, m/s): what
the solve's contact_speed must let through.
"""

from __future__ import annotations

import argparse
import numpy as np

from humotion.sparse import metrics
from humotion.sparse import solve as sv
from humotion.sparse.batches import DEFAULT_DATA
from humotion.sparse.evaluation import FLOOR, prepare, test_sets
from humotion.sparse.recording import stream_from_motion
from humotion.sparse.tracker import SparseTracker, load_weights

TAKES = ("09_",)
"""The takes of the CMU test split on flat ground with the feet moving (subject 09 walks and
runs); subject 03 walks on uneven ground, where contacts with the capture's ground plane say
little, and the others are basketball and dance."""
RULES = {"fixed height (before)": sv.SolveSettings(relative_contact=False), "relative (today)": sv.SolveSettings()}


def solve_online(tracked, stream, settings):
    """(solved world positions (F, J, 3), planted (F, 2) bool): the solve a frame at a time."""
    body, state = sv.BodyGeometry.of(tracked.skeleton), sv.SolveState()
    local, world_p = tracked.rotations.double().numpy(), tracked.world_positions().double().numpy()
    r, p = stream.rotations.double().numpy(), stream.positions.double().numpy()
    visible = stream.visible.numpy().astype(bool)
    out, planted = np.empty_like(world_p), np.zeros((len(local), 2), bool)
    for t in range(len(local)):
        _, out[t:t + 1] = sv.solve_frames(local[t:t + 1], world_p[t:t + 1], body, r[t:t + 1, 1:], p[t:t + 1, 1:],
                                          visible[t:t + 1], p[t:t + 1, 0, 1], tracked.fps, FLOOR, state, settings)
        planted[t] = state.locked
    return out, planted


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default=None, help="network weights (default: the shipped)")
    parser.add_argument("--raise-cm", type=float, default=0.0, help="raise the network's body by this much")
    parser.add_argument("--max-seconds", type=float, default=60.0)
    args = parser.parse_args()
    model = load_weights(args.weights)
    clips = [c for c in test_sets(DEFAULT_DATA)["CMU test"] if c.name.startswith(TAKES)]
    sums = {name: np.zeros(8) for name in RULES}
    network_speed = []
    for clip in clips:
        truth = prepare(clip.load(), model.fps, args.max_seconds)
        if truth is None:
            continue
        stream = stream_from_motion(truth, "MC")
        tracked = SparseTracker(model, runtime="torch", solve=None, floor=FLOOR).track(stream)
        tracked.root_positions[:, 1] += args.raise_cm / 100
        body = sv.BodyGeometry.of(tracked.skeleton)
        true_contacts = sv.foot_contacts(truth.world_positions().double().numpy(),
                                         sv.BodyGeometry.of(truth.skeleton).clearance, FLOOR, truth.fps)
        balls = tracked.world_positions().double().numpy()[:, sv.BALLS][..., [0, 2]]
        speed = np.linalg.norm(np.diff(balls, axis=0), axis=-1) * truth.fps
        network_speed.append(speed[true_contacts[1:]])
        line = [f"{clip.name[:24]:24s} {truth.num_frames:5d} fr, truth {int(true_contacts[1:].sum()):4d} contacts:"]
        for name, settings in RULES.items():
            solved, planted = solve_online(tracked, stream, settings)
            hits = int((planted & true_contacts)[1:].sum())
            skate_truth = np.linalg.norm(np.diff(solved[:, sv.BALLS][..., [0, 2]], axis=0), axis=-1) * truth.fps * 100
            scores = metrics.skating(solved, sv.foot_contacts(solved, body.clearance, FLOOR, truth.fps), truth.fps)
            pen, depth = metrics.penetration(solved, body.clearance, FLOOR)
            sums[name] += [hits, planted[1:].sum(), true_contacts[1:].sum(), skate_truth[true_contacts[1:]].sum(),
                           scores[0] * scores[1] if scores[1] else 0.0, scores[1], pen * len(solved), len(solved)]
            line.append(f"{name.split()[0]} P {hits / max(planted[1:].sum(), 1):.2f} R {hits / max(true_contacts[1:].sum(), 1):.2f}")
        print("  ".join(line), flush=True)
    speeds = np.concatenate(network_speed)
    print(f"\n{len(clips)} takes (a walk, two runs), raised {args.raise_cm:g} cm; network's ball speed on the truth's contact "
          f"frames: median {np.median(speeds):.2f} m/s, 90th percentile {np.percentile(speeds, 90):.2f} m/s")
    print(f"{'rule':24s} {'precision':>9s} {'recall':>7s} {'skate @truth':>13s} {'skate':>7s} {'contacts':>9s} {'pen %':>6s}")
    for name, (hits, planted, true, skate_truth, skate_sum, count, pen, frames) in sums.items():
        print(f"{name:24s} {hits / max(planted, 1):9.3f} {hits / max(true, 1):7.3f} {skate_truth / max(true, 1):13.2f} "
              f"{skate_sum / max(count, 1):7.2f} {int(count):9d} {pen / max(frames, 1):6.2f}")


if __name__ == "__main__":
    main()
