import re,sys,datetime,statistics
log=open(sys.argv[1]).read()
pat=re.compile(r"\[(\d+-\d+-\d+ [\d:.]+)\] \[info\] session (\d+): 'bot-(\d+)' joined")
rows=[(datetime.datetime.strptime(t,"%Y-%m-%d %H:%M:%S.%f"),int(b)) for t,s,b in pat.findall(log)]
if not rows: print("no joins"); sys.exit()
t0=min(t for t,b in rows)
ds=sorted((t-t0).total_seconds()-b/float(sys.argv[2]) for t,b in rows)
print("join delay behind the ramp: p50 %.2f p99 %.2f max %.2f s; over 5 s: %d of %d"%(statistics.median(ds), ds[int(len(ds)*0.99)], ds[-1], sum(1 for x in ds if x>5), len(ds)))
