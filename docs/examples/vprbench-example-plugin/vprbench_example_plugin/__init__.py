"""A method living outside vprbench: grey thumbnails, mean-centred, as global descriptors."""
import numpy as np

import vprbench
from vprbench.images import load_image


class Thumbnail(vprbench.Method):
    def __init__(self, size: int = 16, device: str = "cpu"):
        if isinstance(size, bool) or not isinstance(size, int) or size < 1:  # -o size=abc arrives as a string
            raise vprbench.VPRBenchError(f"thumbnail: option size takes a whole number >= 1; got {size!r}.")
        self.size = size

    def fingerprint(self) -> dict:
        return {"size": self.size}

    def provenance(self) -> dict:
        return {"weights": {"source": "none"}}  # nothing learnt: the official row, not "† weights undeclared"

    def describe(self, images):
        rows = []
        for path in images:
            grey = np.asarray(load_image(path, "L").resize((self.size, self.size)), dtype=np.float32).ravel()
            grey -= grey.mean()
            rows.append(grey / max(np.linalg.norm(grey), 1e-12))
        return np.stack(rows)


def register():
    vprbench.register_method("thumbnail", Thumbnail, description="grey 16x16 thumbnail (example plugin)")
