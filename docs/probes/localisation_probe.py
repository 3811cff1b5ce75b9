# Localisation probe (issue 32 diagnosis, not shipped): can a small conv encoder + spatial
# softmax regress the grasp point (relative to the TCP) from the wrist / ext1 image, from 175
# demos, and how fast? Same trunk as labrig's `ShallowConv`, written again in PyTorch to run
# many variants on a GPU in minutes.
# Usage (on a GPU machine with PyTorch; CPU works, slowly): put probe.npz (from
# localisation_probe_data.py) beside this file, run `python3 localisation_probe.py [variant
# numbers]`; the figures go to $OUT/probe.json (or /tmp/probe.json).
import io, json, sys, time, os
import numpy as np, torch, torch.nn as nn, torch.nn.functional as F
from PIL import Image
torch.backends.cudnn.benchmark = True
dev = 'cuda'
d = np.load(os.path.join(os.path.dirname(__file__), 'probe.npz'))
def unpack(key):
    buf, lens = d[key], d[key + '_len']; out = []; o = 0
    for n in lens:
        out.append(np.asarray(Image.open(io.BytesIO(buf[o:o + n].tobytes())).convert('RGB'))); o += n
    return torch.from_numpy(np.stack(out)).permute(0, 3, 1, 2).contiguous()  # N,3,128,128 u8
imgs = {'wrist': unpack('wrist'), 'ext1': unpack('ext1')}
off = torch.from_numpy(d['offset']); ep = torch.from_numpy(d['episode']); t = torch.from_numpy(d['t'])
train = ep < 175; val = ep >= 175
print('samples', len(off), 'train', int(train.sum()), 'val', int(val.sum()), 'first-step val', int((val & (t == 0)).sum()), flush=True)
base = (off[val & (t == 0)][:, :2] - off[train & (t == 0)][:, :2].mean(0)).norm(dim=1).mean().item() * 1000
print(f'baseline (mean grasp offset, xy) at t=0: {base:.1f} mm', flush=True)

class SpatialSoftmax(nn.Module):
    def __init__(s, c, k):
        super().__init__(); s.kp = nn.Conv2d(c, k, 1); s.temp = nn.Parameter(torch.ones(1))
    def forward(s, x):
        b, _, h, w = x.shape; x = s.kp(x).flatten(2) / s.temp
        a = F.softmax(x, -1)
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, h, device=x.device), torch.linspace(-1, 1, w, device=x.device), indexing='ij')
        return torch.cat([(a * xs.flatten()).sum(-1), (a * ys.flatten()).sum(-1)], -1)

class Enc(nn.Module):
    def __init__(s, width=16, layers=3, k=32):
        super().__init__()
        plan = [(3, width, 2), (width, 2 * width, 2), (2 * width, 2 * width, 1)]
        if layers == 4: plan.append((2 * width, 2 * width, 1))
        mods = []
        for ci, co, st in plan: mods += [nn.Conv2d(ci, co, 3, st, 1, bias=False), nn.GroupNorm(max(co // 8, 1), co), nn.ReLU()]
        s.trunk = nn.Sequential(*mods); s.pool = SpatialSoftmax(2 * width, k); s.out = nn.Linear(2 * k, 2 * k)
    def forward(s, x): return F.relu(s.out(s.pool(s.trunk(x))))

class Probe(nn.Module):
    def __init__(s, cams, **kw):
        super().__init__(); s.encs = nn.ModuleList([Enc(**kw) for _ in cams])
        s.head = nn.Sequential(nn.Linear(64 * len(cams), 128), nn.ReLU(), nn.Linear(128, 3))
    def forward(s, xs): return s.head(torch.cat([e(x) for e, x in zip(s.encs, xs)], -1))

def prep(u8, size, crop, train):
    x = u8.to(dev, non_blocking=True).float() / 255
    if size != 128: x = F.interpolate(x, size=(size, size), mode='bilinear', antialias=True, align_corners=False)
    if crop >= size: return x
    if not train:
        o = (size - crop) // 2; return x[:, :, o:o + crop, o:o + crop]
    n = x.shape[0]; oy = torch.randint(0, size - crop + 1, (n,)); ox = torch.randint(0, size - crop + 1, (n,))
    idx = torch.arange(crop, device=dev)
    rows = (oy.to(dev)[:, None] + idx)[:, None, :, None].expand(n, 3, crop, size)
    x = torch.gather(x, 2, rows)
    cols = (ox.to(dev)[:, None] + idx)[:, None, None, :].expand(n, 3, crop, crop)
    return torch.gather(x, 3, cols)

def augment(xs, ix, jitter, flip):
    y = off[ix].to(dev) / 0.2
    if jitter:
        # colour: a random channel order and brightness per sample (the label does not move)
        n = xs[0].shape[0]
        perm = torch.stack([torch.randperm(3) for _ in range(n)]).to(dev)
        xs = [torch.gather(x, 1, perm[:, :, None, None].expand_as(x)) * (0.8 + 0.4 * torch.rand(n, 1, 1, 1, device=dev)) for x in xs]
    if flip:
        # the wrist camera looks down with image x across the base frame's y: a mirror image is
        # the mirrored scene, whose grasp offset has y negated
        m = torch.rand(xs[0].shape[0], device=dev) < 0.5
        x0 = torch.where(m[:, None, None, None], xs[0].flip(3), xs[0])
        xs = [x0] + xs[1:]
        y = torch.where(m[:, None], y * torch.tensor([1.0, -1.0, 1.0], device=dev), y)
    return xs, y

def run(name, cams=('wrist',), size=64, crop=58, epochs=80, lr=1e-3, bs=128, jitter=False, flip=False, **kw):
    torch.manual_seed(0)
    m = Probe(cams, **kw).to(dev); opt = torch.optim.Adam(m.parameters(), lr)
    ti = torch.nonzero(train).flatten(); vi = torch.nonzero(val).flatten(); v0 = torch.nonzero(val & (t == 0)).flatten()
    scale = 0.2; hist = []; t0 = time.time()
    def evaluate(ix):
        m.eval()
        with torch.no_grad():
            p = m([prep(imgs[c][ix], size, crop, False) for c in cams]) * scale
        m.train(); return ((p.cpu() - off[ix]).norm(dim=1).mean().item() * 1000)
    steps_per_epoch = (len(ti) + bs - 1) // bs
    for e in range(epochs):
        perm = ti[torch.randperm(len(ti))]
        for b in range(steps_per_epoch):
            ix = perm[b * bs:(b + 1) * bs]
            xs, y = augment([prep(imgs[c][ix], size, crop, True) for c in cams], ix, jitter, flip)
            loss = F.mse_loss(m(xs), y)
            opt.zero_grad(); loss.backward(); opt.step()
        if (e + 1) % 10 == 0: hist.append((e + 1, round(evaluate(vi), 1), round(evaluate(v0), 1)))
    m.eval()
    with torch.no_grad():
        p = m([prep(imgs[c][vi], size, crop, False) for c in cams]).cpu() * scale
    err = (p - off[vi]).norm(dim=1) * 1000; dist = off[vi].norm(dim=1) * 1000
    bins = [(0, 50), (50, 100), (100, 150), (150, 200), (200, 300), (300, 1000)]
    by_distance = [(a, b, int(((dist >= a) & (dist < b)).sum()), round(err[(dist >= a) & (dist < b)].mean().item(), 1)) for a, b in bins if ((dist >= a) & (dist < b)).any()]
    r = dict(name=name, cams=cams, size=size, crop=crop, jitter=jitter, flip=flip, kw=kw, steps_per_epoch=steps_per_epoch, history=hist, by_distance_mm=by_distance, seconds=round(time.time() - t0, 1))
    print(json.dumps(r), flush=True); return r

out = []
variants = [
    ('wrist 64/58 (small_vision)', dict()),
    ('wrist 64 no crop', dict(crop=64)),
    ('wrist 96/88', dict(size=96, crop=88)),
    ('wrist 128/116', dict(size=128, crop=116)),
    ('wrist+ext1 64/58 (small_vision cams)', dict(cams=('wrist', 'ext1'))),
    ('wrist 64/58 width 32', dict(width=32)),
    ('wrist 64/60', dict(crop=60)),
    ('wrist 96/90 lr 3e-4', dict(size=96, crop=90, lr=3e-4)),
    ('wrist 64/58 colour jitter', dict(jitter=True)),
    ('wrist 64/58 mirror', dict(flip=True)),
    ('wrist 64/58 colour jitter + mirror', dict(jitter=True, flip=True)),
    ('wrist 64/58 colour jitter + mirror, 160 epochs', dict(jitter=True, flip=True, epochs=160)),
    ('wrist+ext1 64/58 colour jitter + mirror (wrist)', dict(cams=('wrist', 'ext1'), jitter=True, flip=True)),
]
only = sys.argv[1:] 
for i, (name, kw) in enumerate(variants):
    if only and str(i) not in only: continue
    out.append(run(name, **kw))
json.dump(dict(baseline_mm=base, runs=out), open(os.path.join(os.environ.get('OUT', '/tmp'), 'probe.json'), 'w'), indent=1)
