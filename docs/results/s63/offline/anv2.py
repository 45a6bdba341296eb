import json, sys, numpy as np
rows=[json.loads(l) for l in open(sys.argv[1])]
def stats(name, pick):
    for kind in ('sim','hm3d'):
        R=[r for r in rows if r['kind']==kind]
        new=[pick(r) for r in R]
        g=sum(r['err']>2 and n<=2 for r,n in zip(R,new)); l=sum(r['err']<=2 and n>2 for r,n in zip(R,new))
        fx=sum(r['err']>10 and n<=10 for r,n in zip(R,new)); br=sum(r['err']<=10 and n>10 for r,n in zip(R,new))
        med=np.median([n for r,n in zip(R,new) if r['outcome']=='ctl'])
        print(f'{name:28s} {kind:5s} gain {g:3d} loss {l} (~{l*4}) net~{g-4*l:+d} fixed {fx} broke {br} ctl med {med:.3f}')
stats('none', lambda r: r['err'])
stats('R', lambda r: r['R']); stats('mid', lambda r: r['mid']); stats('R2', lambda r: r['R2'])
chs=lambda c: c[0]+c[1]
for m in (0.0, 0.01, 0.02, 0.05):
    stats(f'R if ch drops>{m}', lambda r: r['R'] if chs(r['chR']) < chs(r['chE'])-m else r['err'])
for m in (0.0, -0.01):
    stats(f'R if w2 not below {m}', lambda r: r['R'] if r['w2R'] >= r['w2E']+m else r['err'])
for mv in (1, 2, 3, 5):
    stats(f'R if moved<={mv}', lambda r: r['R'] if r['moved'] <= mv else r['err'])
for nw in (30, 50, 100):
    stats(f'R if walls>={nw}', lambda r: r['R'] if min(r['n'])>=nw else r['err'])
