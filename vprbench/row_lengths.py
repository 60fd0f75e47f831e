"""The lengths a descriptor row may have: what the loader checks a method's rows against and what search
takes for an all-zero row, in one place below both."""
from __future__ import annotations

import numpy as np

#: how far from 1 the length of a row compared by cosine may be (float16/bfloat16 arithmetic rounds it)
UNIT_TOLERANCE = 1e-2
#: a row shorter than this is an all-zero row (an image with nothing to describe): it matches nothing
ZERO_LENGTH = 1e-6
#: the longest row whose inner products stay within float32's range (sqrt of its largest value)
MAX_LENGTH = float(np.sqrt(np.finfo(np.float32).max))
