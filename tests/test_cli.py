

def test_a_fleetslam_process_runs_one_blas_thread_unless_told_otherwise():
    """OpenBLAS's threads for small products wait on each other where robot and cloud share
    cores (docs/benchmarks.md): the package sets one before numpy is imported,
    and keeps a value the environment gives."""
    import os
    import subprocess
    import sys
    code = "import fleetslam, os, numpy; print(os.environ['OPENBLAS_NUM_THREADS'])"
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True, timeout=60)
    assert out.stdout.strip() == "1"
    out = subprocess.run([sys.executable, "-c", code], env={**env, "OPENBLAS_NUM_THREADS": "2"},
                         capture_output=True, text=True, check=True, timeout=60)
    assert out.stdout.strip() == "2"
