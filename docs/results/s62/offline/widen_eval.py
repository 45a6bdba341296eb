import sys, json, time, numpy as np, importlib
from multiprocessing import Pool
from gridmerge.bench import runner
from gridmerge.transforms import SimilarityTransform, corner_error
AL = importlib.import_module('gridmerge.align')
def work(spec):
    run, cid, E, err, outc = spec
    bench = runner.BenchRun.load(run); case = runner.rebuild_case(bench, cid)
    T = np.asarray(case.truth); T = T if T.shape == (3,3) else np.vstack([T,[0,0,1]])
    ca, oa, cb, ob = AL.working_maps(case.a, case.b)
    t = AL.full_to_crop(SimilarityTransform(E), oa, ob)
    t0 = time.perf_counter(); w = AL._widened(ca, cb, t, case.b.resolution / case.a.resolution); dt = time.perf_counter() - t0
    if w is None: return dict(run=run, cid=cid, outcome=outc, err=err, new_err=err, est_wall=None, new_wall=None, dt=round(dt,3))
    pose = AL.crop_to_full(w[0], oa, ob)
    return dict(run=run, cid=cid, outcome=outc, err=err, est_wall=round(w[1][0],3), new_wall=round(w[1][1],3),
                new_err=round(corner_error(pose, T, case.b.shape),2), dt=round(dt,3))
if __name__ == '__main__':
    specs = []
    for f in sys.argv[2:]:
        for l in open(f):
            c = json.loads(l); specs.append((c['run'], c['cid'], np.asarray(c['E']), c['err'], c['outcome']))
    with Pool(2) as p, open(sys.argv[1], 'w') as f:
        for r in p.imap(work, specs):
            f.write(json.dumps(r)+'\n'); f.flush()
    rows=[json.loads(l) for l in open(sys.argv[1])]
    g=dict(prec_gain=0,prec_loss=0,fixed=0,broke=0,moved=0)
    for r in rows:
        o,n=r['err'],r['new_err']
        if r['new_wall'] is None: continue
        g['moved']+=1
        g['prec_gain']+=o>2 and n<=2; g['prec_loss']+=o<=2 and n>2; g['fixed']+=o>10 and n<=10; g['broke']+=o<=10 and n>10
        if (o>2)!=(n>2) or (o>10)!=(n>10): print(r['run'][-14:], r['cid'][-4:], o, '->', n, r['est_wall'], '->', r['new_wall'])
    print(g, 'median dt', np.median([r['dt'] for r in rows]), 'max', max(r['dt'] for r in rows))
