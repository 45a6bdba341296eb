import json,sys,numpy as np
rows=[json.loads(l) for f in sys.argv[1:] for l in open(f) if l.startswith('[')]
pos=[r for r in rows if r[2] is not None and r[3]['e0']==r[3]['e0']]
e0=np.array([r[3]['e0'] for r in pos]); e1=np.array([r[3]['e1'] for r in pos]); thr=np.array([r[2] for r in pos])
print(len(rows),'poses,',len(pos),'positive & movable; applied',sum(r[3]['moved'] is not None and not r[3]['refused'] for r in pos),'refused',sum(r[3]['refused'] for r in rows))
print('precise %d -> %d, right %d -> %d, median %.3f -> %.3f, mean %.3f -> %.3f'%((e0<=2).sum(),(e1<=2).sum(),(e0<=thr).sum(),(e1<=thr).sum(),np.median(e0),np.median(e1),np.minimum(e0,50).mean(),np.minimum(e1,50).mean()))
for r in pos:
    o=r[3]
    if (o['e0']<=2)!=(o['e1']<=2) or (o['e0']<=r[2])!=(o['e1']<=r[2]): print('  ',r[0],r[1][-4:],'%.2f -> %.2f moved %.2f'%(o['e0'],o['e1'],o['moved']))
d=e1-e0; print('nearer',(d<-0.05).sum(),'farther',(d>0.05).sum(),'farther by >0.5',(d>0.5).sum())
