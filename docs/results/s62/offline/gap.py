# For imprecise/wrong positives: despeckled wall agreement at truth vs at the estimate
import sys, json, numpy as np
sys.path.insert(0,'/tmp/s61')
from totals import sim_run, hm3d_run, bend_run
from multiprocessing import Pool
from gridmerge.bench import runner
from gridmerge.verify import verify, despeckle
from gridmerge.transforms import SimilarityTransform
R='/work/main/docs/results'
def runs():
    out=[]
    for s in range(51,122):
        d=sim_run(s) if s<110 else f'{R}/s61/sim_s{s}'
        out.append(d)
    for s in range(39,67):
        out.append(hm3d_run(s) if s<65 else f'{R}/s61/hm3d_s{s}')
    return out
def work(spec):
    run,cid,E,err,outc=spec
    bench=runner.BenchRun.load(run); case=runner.rebuild_case(bench,cid)
    T=np.asarray(case.truth); T=T if T.shape==(3,3) else np.vstack([T,[0,0,1]])
    a,b=despeckle(case.a),despeckle(case.b)
    vt=verify(a,b,SimilarityTransform(T)); ve=verify(a,b,SimilarityTransform(E))
    f=lambda v:(v.walls_a,v.walls_b,round(v.wall_agreement,3) if v.wall_agreement is not None else None)
    return dict(run=run,cid=cid,outcome=outc,err=err,truth=f(vt),est=f(ve))
if __name__=='__main__':
    specs=[]
    for d in runs():
        for l in open(d+'/cases.jsonl'):
            c=json.loads(l)
            if c['method']!='hybrid' or not c['positive'] or c['precise'] or not c['aligned']: continue
            E=np.vstack([np.asarray(c['estimate']['matrix']),[0,0,1]])
            specs.append((d,c['case_id'],E,round(c['corner_error_px'],1),'wrong' if c['wrong'] else 'right'))
    print(len(specs),'cases',file=sys.stderr)
    with Pool(2) as p, open(sys.argv[1],'w') as f:
        for r in p.imap(work,specs):
            f.write(json.dumps(r)+'\n'); f.flush()
            print(r['run'].split('/')[-1],r['cid'][-4:],r['outcome'],r['err'],'truth',r['truth'],'est',r['est'],flush=True)
