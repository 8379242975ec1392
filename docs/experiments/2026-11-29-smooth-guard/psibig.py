import csv, glob, sys
root=sys.argv[1]
for f in sorted(glob.glob(root+"/episodes/**/steps.csv", recursive=True)):
    rows=list(csv.DictReader(open(f)))
    for i,(a,b) in enumerate(zip(rows,rows[1:])):
        j=(float(b['heading_rate'])-float(a['heading_rate']))/(float(b['time'])-float(a['time']))
        if abs(j)>2:
            print(f.split('/')[-2], a['step'], 'j=%.2f'%j, 'v=%.1f'%float(a['v']), 'rate %.2f->%.2f'%(float(a['heading_rate']),float(b['heading_rate'])), 'cmd a=%.2f st=%.3f'%(float(a['command_acceleration']),float(a['command_steering'])), 'fs',a['failsafe'],'ver',a['verified'],'goal',a['goal_index'])
