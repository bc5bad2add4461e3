import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
threads=[1,2,4,8,16]
old=[30.52,16.35,10.39,7.40,4.88]      # vlf propagate, propagate_s, before (chunk meetings / homes)
new=[28.81,15.39,8.15,4.07,2.43]       # vlf propagate, propagate_s, claimed directions
workers=[1,2,4,8]
wk=[18.572,10.068,6.138,3.483]         # vlf bench --scaling, iterations s, 2 threads a worker
fig,ax=plt.subplots(1,2,figsize=(10,4))
ax[0].plot(threads,[old[0]/t for t in old],"o-",label="before: chunks of 16 shared, homes")
ax[0].plot(threads,[new[0]/t for t in new],"s-",label="claimed directions (now)")
ax[0].plot(threads,threads,"k:",label="linear")
ax[0].set_xscale("log",base=2); ax[0].set_yscale("log",base=2)
ax[0].set_xticks(threads); ax[0].set_xticklabels(threads); ax[0].set_yticks(threads); ax[0].set_yticklabels(threads)
ax[0].set_xlabel("threads in one process"); ax[0].set_ylabel("speed-up over 1 thread")
ax[0].set_title("vlf propagate, Cornell box l=2049 N=128"); ax[0].legend(fontsize=8); ax[0].grid(alpha=.3)
ax[1].plot(workers,[wk[0]/t for t in wk],"s-",color="C1",label="embedded service, 2 threads a worker")
ax[1].plot(workers,workers,"k:",label="linear")
ax[1].set_xscale("log",base=2); ax[1].set_yscale("log",base=2)
ax[1].set_xticks(workers); ax[1].set_xticklabels(workers); ax[1].set_yticks(workers); ax[1].set_yticklabels(workers)
ax[1].set_xlabel("workers"); ax[1].set_ylabel("speed-up over 1 worker (iterations)")
ax[1].set_title("vlf bench --scaling, same job"); ax[1].legend(fontsize=8); ax[1].grid(alpha=.3)
fig.suptitle("16-core host of the device tool (Intel Xeon, NVIDIA H100 machine)",fontsize=9)
fig.tight_layout(); fig.savefig("scaling.png",dpi=90)
