import sys, json, time, numpy as np, importlib
sys.path.insert(0,'/tmp/s61')
from totals import part_run
from multiprocessing import Pool
from gridmerge.bench import runner
from gridmerge.bench.metrics import halmstad_point_error
from gridmerge.transforms import SimilarityTransform
AL = importlib.import_module('gridmerge.align')
def work(spec):
    run, cid, E, err, outc, thr = spec
    bench = runner.BenchRun.load(run); case = runner.rebuild_case(bench, cid)
    ca, oa, cb, ob = AL.working_maps(case.a, case.b)
    t = AL.full_to_crop(SimilarityTransform(E), oa, ob)
    w = AL._widened(ca, cb, t, case.b.resolution / case.a.resolution)
    if w is None: return dict(run=run, cid=cid, outcome=outc, err=err, new_err=err, thr=thr, moved=False)
    pose = AL.crop_to_full(w[0], oa, ob)
    if case.positive:
        ne = halmstad_point_error(pose, np.asarray(case.meta['points_a']), np.asarray(case.meta['points_b']))
    else: ne = None
    return dict(run=run, cid=cid, outcome=outc, err=err, new_err=ne, thr=thr, moved=True, walls=w[1])
if __name__ == '__main__':
    specs = []
    for s in range(3, 28):
        d = part_run(s)
        for l in open(d + '/cases.jsonl'):
            c = json.loads(l)
            if c['method'] != 'hybrid' or not c['aligned']: continue
            E = np.vstack([np.asarray(c['estimate']['matrix']), [0, 0, 1]])
            specs.append((d, c['case_id'], E, c.get('point_error_px'), 'wrong' if c['wrong'] else 'false' if c['false_merge'] else 'right', c.get('threshold_px')))
    print(len(specs), flush=True)
    with Pool(2) as p, open(sys.argv[1], 'w') as f:
        for r in p.imap(work, specs):
            f.write(json.dumps(r) + '\n'); f.flush()
            if r['moved']: print(r, flush=True)
