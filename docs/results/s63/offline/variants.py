import sys, json, numpy as np
sys.path.insert(0,'/tmp/s63')
from diag import *
from multiprocessing import Pool
VARS={'h1t3':(1,3),'h.5t2':(0.5,2),'h1t2':(1,2),'h2t4':(2,4),'h.5t3':(0.5,3),'h.3t1.5':(0.3,1.5)}
def work3(spec):
    run, cid, E, err, outc, kind = spec
    bench = runner.BenchRun.load(run); case = runner.rebuild_case(bench, cid)
    Tm = np.asarray(case.truth)
    ca, oa, cb, ob = AL.working_maps(case.a, case.b)
    E = np.asarray(E); E = E if E.shape==(3,3) else np.vstack([E,[0,0,1]])
    tE = AL.full_to_crop(SimilarityTransform(E), oa, ob)
    ch = Chamfer(ca, cb)
    out = dict(run=run[-14:], cid=cid[-4:], outcome=outc, kind=kind, err=round(err,3))
    for k,(h,t) in VARS.items():
        R = SimilarityTransform(ch.refine(tE.params, huber=h, trunc=t))
        out[k] = round(corner_error(AL.crop_to_full(R, oa, ob), Tm, case.b.shape), 3)
    return out
if __name__ == '__main__':
    specs=[]
    for l in open(sys.argv[2]):
        c=json.loads(l); specs.append((c['run'], c['cid'], c['E'], c['err'], c['outcome'], c['kind']))
    with Pool(2) as p, open(sys.argv[1],'w') as f:
        for r in p.imap_unordered(work3, specs): f.write(json.dumps(r)+'\n'); f.flush()
