# offline: the new _midway step applied to stored taken poses, exactly as _align would (reference frame)
import sys, json, numpy as np
from multiprocessing import Pool
from gridmerge.bench import runner
from gridmerge.bench.metrics import halmstad_point_error
from gridmerge.transforms import corner_error, SimilarityTransform
import importlib; AL=importlib.import_module("gridmerge.align")
from gridmerge.verify import verify
def work(args):
    run,cid=args
    bench=runner.BenchRun.load(run); case=runner.rebuild_case(bench,cid)
    rec=[c for c in (json.loads(l) for l in open(run+'/cases.jsonl')) if c['case_id']==cid and c['method']=='hybrid'][0]
    M=np.vstack([np.asarray(rec['estimate']['matrix']),[0,0,1]])
    prot=case.meta if case.meta.get('protocol')=='halmstad' else None
    if not case.positive:
        err=lambda m: float('nan')
    elif prot is None:
        T=np.asarray(case.truth); err=lambda m: corner_error(m,T,case.b.shape)
    else:
        err=lambda m: halmstad_point_error(m,prot['points_a'],prot['points_b'])
    a,b,t=case.a,case.b,SimilarityTransform(M)
    swap=not AL.reference_first(a,b)
    if swap: a,b,t=b,a,t.inverse
    opts=AL.AlignOptions()
    ca,oa,cb,ob=AL.working_maps(a,b)
    out={'e0':err(M),'e1':err(M),'moved':None,'refused':False}
    if str(rec['details'].get('walls','')).startswith('skipped') or (AL._scale_disagreement(t,a,b)>AL._SCALE_PRIOR_RANGE-1.0): 
        return run.split('/')[-1],cid,None,out
    tc=AL.full_to_crop(t,oa,ob)
    r=AL._midway(a,b,ca,cb,tc)
    if r is not None:
        pose,moved=r; out['moved']=moved
        chk=verify(ca,cb,pose,tolerance=opts.wall_tolerance)
        ratio=rec['details'].get('runner_up_ratio') if 'confirmed_by' not in rec['details'] else None
        if AL._decline_reason(rec['inliers'],chk,rec['confidence'],opts,need_inliers=False,scale_off=AL._scale_disagreement(pose,ca,cb),matched='confirmed_by' in rec['details'],runner_up_ratio=ratio):
            out['refused']=True
        else:
            f=AL.crop_to_full(pose,oa,ob)
            if swap: f=f.inverse
            out['e1']=err(np.asarray(f.params))
    thr=prot['threshold_px'] if prot else 10.0
    return run.split('/')[-1],cid,thr,out
if __name__=='__main__':
    jobs=[]
    for run in sys.argv[1:]:
        for l in open(run+'/cases.jsonl'):
            c=json.loads(l)
            if c['method']=='hybrid' and c['aligned'] and not str(c['details'].get('walls','')).startswith('skipped'):
                jobs.append((run,c['case_id']))
    print(len(jobs),'jobs',flush=True)
    with Pool(2) as p:
        for r in p.imap_unordered(work,jobs):
            print(json.dumps(r),flush=True)
