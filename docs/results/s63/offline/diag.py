import sys, json, time, numpy as np, importlib, cv2
from multiprocessing import Pool
from gridmerge.bench import runner
from gridmerge.transforms import SimilarityTransform, corner_error
from gridmerge.verify import verify
AL = importlib.import_module('gridmerge.align')

def dt(mask):
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)

def pts(mask):
    y, x = np.nonzero(mask); return np.column_stack([x, y]).astype(float)

def apply(M, p): return p @ M[:2, :2].T + M[:2, 2]

def sample(img, p, cval=1e3):
    if len(p) == 0: return np.zeros(0)
    h, w = img.shape
    x, y = p[:, 0], p[:, 1]
    x0 = np.floor(x).astype(np.int64); y0 = np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    out = np.full(len(p), float(cval))
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    x0, y0, fx, fy = x0[ok], y0[ok], fx[ok], fy[ok]
    f = img.astype(float, copy=False)
    out[ok] = (f[y0, x0]*(1-fx)*(1-fy) + f[y0, x0+1]*fx*(1-fy) + f[y0+1, x0]*(1-fx)*fy + f[y0+1, x0+1]*fx*fy)
    return out

class Chamfer:
    def __init__(self, a, b, trunc=3.0):
        self.wa, self.wb = a.occupied(), b.occupied()
        self.da, self.db = dt(self.wa), dt(self.wb)
        self.ka, self.kb = a.known, b.known
        self.pa, self.pb = pts(self.wa), pts(self.wb)
        self.trunc = trunc
    def sides(self, M):
        Mi = np.linalg.inv(M)
        qb = apply(M, self.pb)  # b walls in a
        inb = sample(self.ka.astype(float), qb, 0) > 0.5
        qa = apply(Mi, self.pa)  # a walls in b
        ina = sample(self.kb.astype(float), qa, 0) > 0.5
        s = np.sqrt(abs(np.linalg.det(M[:2, :2])))
        return sample(self.da, qb[inb]), sample(self.db, qa[ina]) * s
    def score(self, M):
        r1, r2 = self.sides(M)
        f = lambda r: np.minimum(r, self.trunc).mean() if len(r) else np.nan
        return f(r1), f(r2), len(r1), len(r2)
    def fixed(self, M):
        self._in = None
        Mi = np.linalg.inv(M)
        qb = apply(M, self.pb); self.ib = self.pb[sample(self.ka.astype(float), qb, 0) > 0.5]
        qa = apply(Mi, self.pa); self.ia = self.pa[sample(self.kb.astype(float), qa, 0) > 0.5]
    def refine(self, M, iters=30, huber=1.0, trunc=3.0):
        s = np.sqrt(abs(np.linalg.det(M[:2, :2]))); th = np.arctan2(M[1, 0], M[0, 0]); tx, ty = M[0, 2], M[1, 2]
        self.fixed(M)
        ga = [cv2.Sobel(self.da, cv2.CV_32F, 1, 0, ksize=3)/8, cv2.Sobel(self.da, cv2.CV_32F, 0, 1, ksize=3)/8]
        gb = [cv2.Sobel(self.db, cv2.CV_32F, 1, 0, ksize=3)/8, cv2.Sobel(self.db, cv2.CV_32F, 0, 1, ksize=3)/8]
        def mat(th, tx, ty):
            c, si = s*np.cos(th), s*np.sin(th)
            return np.array([[c, -si, tx], [si, c, ty], [0, 0, 1.0]])
        def cost(th, tx, ty):
            Mm = mat(th, tx, ty)
            r1 = sample(self.da, apply(Mm, self.ib)); r2 = sample(self.db, apply(np.linalg.inv(Mm), self.ia)) * s
            h = lambda r: np.where(np.abs(r) <= huber, 0.5*r*r, huber*(np.abs(r)-0.5*huber)).clip(max=huber*(trunc-0.5*huber)).mean() if len(r) else 0.0
            return h(r1) + h(r2)
        for _ in range(iters):
            Mm = mat(th, tx, ty)
            # side 1: b walls -> a; params th,tx,ty
            q = apply(Mm, self.ib); r1 = sample(self.da, q)
            gx, gy = sample(ga[0], q), sample(ga[1], q)
            # d q / d th = [-s sin x - s cos y, s cos x - s sin y] = R'(p)
            c, si = s*np.cos(th), s*np.sin(th); x, y = self.ib[:, 0], self.ib[:, 1]
            dqx, dqy = -si*x - c*y, c*x - si*y
            J1 = np.column_stack([gx*dqx + gy*dqy, gx, gy])
            # side 2: a walls -> b: p = Mi(q); residual s*db(Mi q)
            Mi = np.linalg.inv(Mm); p = apply(Mi, self.ia); r2 = sample(self.db, p) * s
            hx, hy = sample(gb[0], p)*s, sample(gb[1], p)*s
            # p = R^-1 (q - t)/s ; dp/dt = -R^-1/s ; dp/dth = d/dth R(-th)(q-t)/s
            ct, st = np.cos(th), np.sin(th); u = self.ia[:, 0]-tx; v = self.ia[:, 1]-ty
            dpx_th = (-st*u + ct*v)/s; dpy_th = (-ct*u - st*v)/s
            dpx_tx, dpy_tx = -ct/s, st/s; dpx_ty, dpy_ty = -st/s, -ct/s
            J2 = np.column_stack([hx*dpx_th + hy*dpy_th, hx*dpx_tx + hy*dpy_tx, hx*dpx_ty + hy*dpy_ty])
            r = np.concatenate([r1, r2]); J = np.vstack([J1, J2])
            wts = np.concatenate([np.full(len(r1), 1/max(len(r1),1)), np.full(len(r2), 1/max(len(r2),1))])
            ar = np.abs(r); w = wts * np.where(ar <= huber, 1.0, huber/np.maximum(ar, 1e-9)) * (ar < trunc)
            H = (J*w[:, None]).T @ J + np.diag([1e-6*s*s*1e4, 1e-6, 1e-6]); g = (J*w[:, None]).T @ r
            d = -np.linalg.solve(H, g)
            c0 = cost(th, tx, ty); ok = False
            for _h in range(6):
                if cost(th + d[0], tx + d[1], ty + d[2]) < c0:
                    ok = True; break
                d = d / 2
            if not ok: break
            th, tx, ty = th + d[0], tx + d[1], ty + d[2]
            if abs(d[0]) < 1e-6 and abs(d[1]) < 1e-3 and abs(d[2]) < 1e-3: break
        return mat(th, tx, ty)

def work(spec):
    run, cid, E, err, outc, kind = spec
    bench = runner.BenchRun.load(run); case = runner.rebuild_case(bench, cid)
    Tm = np.asarray(case.truth); Tm = Tm if Tm.shape == (3,3) else np.vstack([Tm,[0,0,1]])
    ca, oa, cb, ob = AL.working_maps(case.a, case.b)
    tE = AL.full_to_crop(SimilarityTransform(np.asarray(E) if np.asarray(E).shape==(3,3) else np.vstack([E,[0,0,1]])), oa, ob)
    tT = AL.full_to_crop(SimilarityTransform(Tm), oa, ob)
    ch = Chamfer(ca, cb)
    out = dict(run=run[-14:], cid=cid[-4:], outcome=outc, kind=kind, err=round(err,2))
    for name, t in (('E', tE), ('T', tT)):
        v2 = verify(ca, cb, t, tolerance=2); v1 = verify(ca, cb, t, tolerance=1)
        c = ch.score(t.params)
        out[name] = dict(w2=round(v2.wall_agreement,4), w1=round(v1.wall_agreement,4), ai=round(v2.acceptance_index,4), c1=round(c[0],3), c2=round(c[1],3), n=(c[2], c[3]))
    t0 = time.perf_counter()
    R = ch.refine(tE.params)
    out['dt'] = round(time.perf_counter()-t0, 3)
    pose = AL.crop_to_full(SimilarityTransform(R), oa, ob)
    out['ref_err'] = round(corner_error(pose, Tm, case.b.shape), 2)
    c = ch.score(R); v2 = verify(ca, cb, SimilarityTransform(R), tolerance=2)
    out['R'] = dict(w2=round(v2.wall_agreement,4), c1=round(c[0],3), c2=round(c[1],3))
    return out

if __name__ == '__main__':
    specs = []
    for l in open(sys.argv[2]):
        c = json.loads(l); specs.append((c['run'], c['cid'], c['E'], c['err'], c['outcome'], c['kind']))
    if len(sys.argv) > 3: specs = specs[:int(sys.argv[3])]
    with Pool(2) as p, open(sys.argv[1], 'w') as f:
        for r in p.imap_unordered(work, specs):
            f.write(json.dumps(r)+'\n'); f.flush()
