import sys, json, numpy as np
sys.path.insert(0,'/tmp/s63')
from diag import *
from multiprocessing import Pool
def work4(spec):
    run, cid, E, err, outc, kind = spec
    bench = runner.BenchRun.load(run); case = runner.rebuild_case(bench, cid)
    Tm = np.asarray(case.truth)
    ca, oa, cb, ob = AL.working_maps(case.a, case.b)
    E = np.asarray(E); E = E if E.shape==(3,3) else np.vstack([E,[0,0,1]])
    tE = AL.full_to_crop(SimilarityTransform(E), oa, ob)
    ch = Chamfer(ca, cb)
    out = dict(run=run[-14:], cid=cid[-4:], outcome=outc, kind=kind, err=round(err,3))
    err_of = lambda M: round(corner_error(AL.crop_to_full(SimilarityTransform(M), oa, ob), Tm, case.b.shape), 3)
    R = ch.refine(tE.params, huber=0.5, trunc=3)
    R2 = ch.refine(R, huber=0.5, trunc=3)
    out['R'] = err_of(R); out['mid'] = err_of((R + tE.params)/2); out['R2'] = err_of(R2)
    out['moved'] = round(corner_error(SimilarityTransform(R), tE, cb.shape), 3)
    sE, sR = ch.score(tE.params), ch.score(R)
    out['chE'] = [round(sE[0],4), round(sE[1],4)]; out['chR'] = [round(sR[0],4), round(sR[1],4)]; out['n'] = [sE[2], sE[3]]
    out['w2E'] = round(verify(ca, cb, tE, tolerance=2).wall_agreement, 4); out['w2R'] = round(verify(ca, cb, SimilarityTransform(R), tolerance=2).wall_agreement, 4)
    return out
if __name__ == '__main__':
    specs=[]
    for l in open(sys.argv[2]):
        c=json.loads(l); specs.append((c['run'], c['cid'], c['E'], c['err'], c['outcome'], c['kind']))
    with Pool(2) as p, open(sys.argv[1],'w') as f:
        for r in p.imap_unordered(work4, specs): f.write(json.dumps(r)+'\n'); f.flush()
