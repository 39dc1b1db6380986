"""peak_rss_mb reports this process's own peak, not the one of the process that started it."""

import subprocess
import sys

import numpy as np

from trianflow_vo.io.run_writer import peak_rss_mb


def test_a_child_of_a_large_process_reports_its_own_peak():
    big = np.ones(40_000_000)  # ~300 MB resident in this process
    assert peak_rss_mb() > 250
    code = "from trianflow_vo.io.run_writer import peak_rss_mb; print(peak_rss_mb())"
    child = float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
    del big
    assert 0 < child < 200, child  # ru_maxrss would have said ~300 MB (inherited through fork + exec)
