"""``evchain bench`` times its workloads with every BLAS library on one thread, also those that
a workload loads only when it runs (scipy's own OpenBLAS, through the bar's error function):
idle OpenBLAS workers spin, and CPU time would count them."""

import json
import subprocess
import sys

SCRIPT = """
import json
import numpy
from threadpoolctl import threadpool_info
from evchain.bench import one_blas_thread
from evchain.benchmarks.emulator import scene_frames
with one_blas_thread():
    scene_frames("bar", 3, 32, 24)        # imports scipy.special inside the limit
    print(json.dumps([(i["filepath"], i["num_threads"]) for i in threadpool_info()
                      if i["user_api"] == "blas"]))
"""


def test_every_blas_library_runs_on_one_thread_in_a_fresh_interpreter():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                         check=True).stdout
    libs = json.loads(out.strip().splitlines()[-1])
    assert libs and all(n == 1 for _, n in libs), libs
