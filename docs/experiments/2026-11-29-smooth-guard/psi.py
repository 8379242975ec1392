import csv, glob, sys, statistics as st
for root in sys.argv[1:]:
    allj=[]; big=[]; fs=0
    for f in sorted(glob.glob(root+"/episodes/**/steps.csv", recursive=True)):
        rows=list(csv.DictReader(open(f)))
        for a,b in zip(rows,rows[1:]):
            dt=float(b['time'])-float(a['time'])
            j=(float(b['heading_rate'])-float(a['heading_rate']))/dt
            allj.append(abs(j))
            # command at step a produced the change
            inside = a['failsafe']=='True' or abs(float(a['command_acceleration'])+5.0)<1e-6
            if abs(j)>5 and not inside: big.append((f.split('/')[-2],a['step'],round(j,2)))
            fs+= inside
    print(root, "steps",len(allj),"mean|psi''|",round(st.mean(allj),4),"max",round(max(allj),2),"n>5 outside fs",len(big),"fs-ish steps",fs, big[:6])
