import sys, json, math, numpy as np, cv2, time
from multiprocessing import Pool
from gridmerge.bench import runner
from gridmerge.verify import verify, despeckle
from gridmerge.transforms import SimilarityTransform, corner_error
from gridmerge.refine import WallICP

def local_search(a, b, E, rot=2.0, rstep=0.25, shift=20, npts=1500, topk=6, tol=2.0):
    wa = a.occupied()
    near = (cv2.distanceTransform((~wa).astype(np.uint8), cv2.DIST_L2, 3) <= tol)
    H, W = near.shape
    P = shift + 2
    pad = np.zeros((H + 2*P, W + 2*P), np.uint8); pad[P:P+H, P:P+W] = near
    flat = pad.ravel(); Wp = W + 2*P
    yb, xb = np.nonzero(b.occupied())
    pts = np.column_stack([xb, yb]).astype(float)
    m = E.params
    q = pts @ m[:2, :2].T + m[:2, 2]
    ka = a.known
    qi = np.rint(q).astype(int)
    ins = (qi[:,0]>=0)&(qi[:,0]<W)&(qi[:,1]>=0)&(qi[:,1]<H)
    ins[ins] = ka[qi[ins,1], qi[ins,0]]
    pts = pts[ins]
    if len(pts) < 10: return None
    if len(pts) > npts: pts = pts[np.linspace(0, len(pts)-1, npts).astype(int)]
    q = pts @ m[:2, :2].T + m[:2, 2]
    c = q.mean(0)
    d = np.arange(-shift, shift+1)
    offs = (d[:,None]*Wp + d[None,:]).ravel()   # dy*Wp + dx
    res = []
    for th in np.arange(-rot, rot+1e-9, rstep):
        t = math.radians(th); R = np.array([[math.cos(t), -math.sin(t)],[math.sin(t), math.cos(t)]])
        r = (q - c) @ R.T + c
        ri = np.rint(r).astype(int)
        ok = (ri[:,0] >= -2) & (ri[:,0] < W+2) & (ri[:,1] >= -2) & (ri[:,1] < H+2)
        base = (ri[ok,1]+P)*Wp + ri[ok,0]+P
        cnt = flat.take(base[None,:] + offs[:,None]).sum(1)
        for k in np.argsort(cnt)[::-1][:3]:
            dy, dx = divmod(k, len(d))
            res.append((int(cnt[k]), th, d[dx], d[dy]))
    res.sort(reverse=True)
    picked = []
    for cnt, th, dx, dy in res:
        if any(abs(th-p[1]) < 0.6 and abs(dx-p[2]) <= 3 and abs(dy-p[3]) <= 3 for p in picked): continue
        picked.append((cnt, th, dx, dy))
        if len(picked) >= topk: break
    out = []
    for cnt, th, dx, dy in picked:
        t = math.radians(th); R = np.array([[math.cos(t), -math.sin(t)],[math.sin(t), math.cos(t)]])
        M = np.eye(3); M[:2,:2] = R; M[:2,2] = c + np.array([dx,dy]) - R @ c
        out.append((cnt, SimilarityTransform(M @ m)))
    return out

def work(spec):
    run, cid, E, err, outc = spec
    bench = runner.BenchRun.load(run); case = runner.rebuild_case(bench, cid)
    T = np.asarray(case.truth); T = T if T.shape == (3,3) else np.vstack([T,[0,0,1]])
    a, b = despeckle(case.a), despeckle(case.b)
    E = SimilarityTransform(E)
    t0 = time.perf_counter()
    ve = verify(a, b, E)
    cands = local_search(a, b, E) or []
    icp = WallICP(a, b)
    best = None
    for cnt, t in cands:
        p = icp.polish(t)
        v = verify(a, b, p)
        if best is None or v.wall_agreement > best[0]:
            best = (v.wall_agreement, p, cnt, v)
    dt = time.perf_counter() - t0
    if best is None: return dict(run=run, cid=cid, outcome=outc, err=err, est_wall=ve.wall_agreement, new=None, dt=dt)
    return dict(run=run, cid=cid, outcome=outc, err=err, est_wall=round(ve.wall_agreement,3), est_n=(ve.walls_a, ve.walls_b),
                new_wall=round(best[0],3), new_n=(best[3].walls_a, best[3].walls_b), new_err=round(corner_error(best[1], T, case.b.shape),2), dt=round(dt,2))

if __name__ == '__main__':
    specs = []
    for l in open(sys.argv[1]):
        c = json.loads(l); specs.append((c['run'], c['cid'], np.asarray(c['E']), c['err'], c['outcome']))
    with Pool(2) as p, open(sys.argv[2], 'w') as f:
        for r in p.imap(work, specs):
            f.write(json.dumps(r)+'\n'); f.flush()
            print(r['run'].split('/')[-1], r['cid'][-4:], r['outcome'], r['err'], r.get('est_wall'), r.get('est_n'), '->', r.get('new_wall'), r.get('new_n'), r.get('new_err'), r['dt'], flush=True)
