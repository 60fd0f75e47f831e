"""`python -m vprbench ...`, which is what `torchrun -m vprbench evaluate ...` starts on every rank."""
import sys

from .cli.main import main

sys.exit(main())
