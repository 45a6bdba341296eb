# store matrices: taken pose M, ICP raw in a-frame (A) and b-frame (B), truth/points; for offline combos
import sys, json, numpy as np, importlib
from multiprocessing import Pool
from gridmerge.bench import runner
from gridmerge.transforms import SimilarityTransform
from gridmerge.refine import WallICP
AL=importlib.import_module('gridmerge.align')
def work(args):
    run,cid=args
    bench=runner.BenchRun.load(run); case=runner.rebuild_case(bench,cid)
    if not case.positive: return None
    rec=[c for c in (json.loads(l) for l in open(run+'/cases.jsonl')) if c['case_id']==cid and c['method']=='hybrid'][0]
    M=np.vstack([np.asarray(rec['estimate']['matrix']),[0,0,1]])
    prot=case.meta if case.meta.get('protocol')=='halmstad' else None
    ra,oa,rb,ob=AL.working_maps(case.a,case.b,despeckled=False)
    tc=AL.full_to_crop(SimilarityTransform(M),oa,ob)
    A=np.asarray(AL.crop_to_full(WallICP(ra,rb).polish(tc),oa,ob).params)
    B=np.asarray(AL.crop_to_full(WallICP(rb,ra).polish(tc.inverse).inverse,oa,ob).params)
    return dict(run=run.split('/')[-1],cid=cid,M=M.tolist(),A=A.tolist(),B=B.tolist(),T=None if prot else np.asarray(case.truth).tolist(),
                pa=prot and np.asarray(prot['points_a']).tolist(),pb=prot and np.asarray(prot['points_b']).tolist(),thr=prot['threshold_px'] if prot else 10.0,
                bshape=list(case.b.shape),cbshape=list(rb.shape),ref_a=bool(AL.reference_first(case.a,case.b)),res=[case.a.resolution,case.b.resolution],
                walls=rec['verification']['walls_a']+rec['verification']['walls_b'],src=rec['details'].get('source'),skipped=str(rec['details'].get('walls','')).startswith('skipped'))
if __name__=='__main__':
    jobs=[]
    for run in sys.argv[1:]:
        for l in open(run+'/cases.jsonl'):
            c=json.loads(l)
            if c['method']=='hybrid' and c['aligned'] and c['positive'] and not str(c['details'].get('walls','')).startswith('skipped'):
                jobs.append((run,c['case_id']))
    print(len(jobs),'jobs',flush=True)
    with Pool(2) as p:
        for r in p.imap_unordered(work,jobs):
            if r: print(json.dumps(r),flush=True)
