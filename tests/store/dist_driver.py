"""`vprbench ...` as torchrun starts it on every rank, with the test methods registered.

    python -m torch.distributed.run --standalone --nproc-per-node 2 dist_driver.py evaluate ...

`{rank}` in an argument becomes the rank (to make ranks disagree on purpose). $KILL_RANK:
that rank SIGKILLs itself at describe call $KILL_AT_BATCH. $LOG gets `.rank<r>` appended.
"""
import os
import sys

import store_helpers
from vprbench.cli.main import main

store_helpers.register_all()
rank = os.environ.get("RANK", "0")
if os.environ.get("KILL_RANK") != rank:
    os.environ.pop("KILL_AT_BATCH", None)
if os.environ.get("LOG"):
    os.environ["LOG"] += f".rank{rank}"
sys.exit(main([argument.replace("{rank}", rank) for argument in sys.argv[1:]]))
