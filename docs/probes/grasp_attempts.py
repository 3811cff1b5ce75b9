# Grasp attempts per rollout (docs/policy_results.md, issue 32): for each `labrig rollout --out`
# directory, every close of the gripper command with the TCP's distance from the cube's
# starting position in the table plane, the gripper's highest reading before the arm rose
# 5 mm (>= 0.8: shut on nothing, a miss), and the outcome.
# `python grasp_attempts.py <rollout out dir>...` with the readers venv (mcap, mcap-ros2-support).
import sys, glob, json, math
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

def scene_object(r):
    for m in r.iter_metadata():
        for v in m.metadata.values():
            if 'object_position' not in v:
                continue
            try:
                x = json.loads(v); s = x.get('sim_scene', x)
                if isinstance(s, str): s = json.loads(s)
                return s['object_position']
            except Exception:
                pass
    return None

def attempts(path):
    with open(path, 'rb') as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        obj = scene_object(r)
        steps = [(list(d.robot_state.cartesian_position[:3]), d.action.gripper_position, d.robot_state.gripper_position)
                 for _, _, _, d in r.iter_decoded_messages(topics=['/rig/step'])]
    out = []
    for c in range(1, len(steps)):
        if not (steps[c][1] > 0.5 >= steps[c - 1][1]):
            continue
        z0 = steps[c][0][2]
        k = c
        shut = 0.0
        while k < len(steps) and steps[k][1] > 0.5 and steps[k][0][2] < z0 + 0.005:
            shut = max(shut, steps[k][2]); k += 1
        d = 1000 * math.hypot(steps[c][0][0] - obj[0], steps[c][0][1] - obj[1]) if obj else float('nan')
        out.append((c, d, shut))
    return out, len(steps)

for d in sys.argv[1:]:
    report = json.load(open(d + '/rollouts.json'))
    rolls = report.get('rollouts', report) if isinstance(report, dict) else report
    paths = sorted(glob.glob(d + '/rollouts/*/*/*/episode_0.mcap'))
    print(f'== {d}: {len(paths)} recorded rollouts')
    n_first_miss = n_recovered = 0
    for p in paths:
        a, n = attempts(p)
        ok = n < 300
        misses = [x for x in a if x[2] >= 0.8]
        first_miss = bool(a) and a[0][2] >= 0.8
        n_first_miss += first_miss
        n_recovered += first_miss and ok
        print(f'{p.split("/")[-2][:40]:40s} steps {n:3d} {"success" if ok else "failure"}  closes: ' +
              ', '.join(f'step {c} {dd:.0f} mm {"MISS" if s >= 0.8 else "held"} ({s:.2f})' for c, dd, s in a))
    print(f'first grasp missed: {n_first_miss}; of those succeeded after: {n_recovered}')
