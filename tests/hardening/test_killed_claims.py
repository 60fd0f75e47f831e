"""A `vprbench run` killed (kill -9) while it holds a cell: the rerun on the same host takes the cell over
at once, never while its holder lives. Was: the rerun waited out the whole lease (120 s by default),
'1 held by other processes', for a process that no longer existed."""
from __future__ import annotations

import signal
import subprocess
import sys

#: claims the cell, says so on stdout, then holds it until killed
HOLDER = """
import sys
from vprbench.sweep.claims import Claims
claims = Claims(sys.argv[1], lease_s=600)
print(claims.claim("cell", lambda: False)[0], claims.worker, flush=True)
sys.stdin.read()
"""


def test_a_cell_of_a_killed_run_is_taken_over_at_once_and_a_live_ones_never(tmp_path):
    from vprbench.sweep.claims import Claims

    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    claims = Claims(tmp_path, lease_s=600)
    try:
        state, worker = holder.stdout.readline().split()
        assert state == "claimed"
        assert claims.claim("cell", lambda: False) == ("busy", worker)  # alive, its lease fresh: never taken
        holder.send_signal(signal.SIGKILL)
        assert holder.wait(timeout=60) == -9
        assert claims.claim("cell", lambda: False) == ("claimed", f"taken over from {worker} (its process has ended)")
        assert claims.still_mine("cell")
        other = Claims(tmp_path, lease_s=600)  # a third process (here: of this one) sees the new holder alive
        try:
            assert other.claim("cell", lambda: False) == ("busy", claims.worker)
        finally:
            other.close()
        claims.release("cell")
        assert sorted(p.name for p in (tmp_path / "sweeps" / "claims").iterdir()) == ["cell.lock"]
    finally:
        holder.kill()
        holder.wait()
        claims.close()
