import json
from pathlib import Path

import pytest
import torch

CHECKPOINT_LAYOUTS = Path(__file__).resolve().parents[1] / "data" / "checkpoints"


def official_state_dict(name: str, variant: str, seed: int = 0) -> dict:
    """Random tensors with the official names and shapes (batch-norm variances kept positive)."""
    layout = json.loads((CHECKPOINT_LAYOUTS / f"{name}.json").read_text())["models"][variant]
    generator = torch.Generator().manual_seed(seed)
    state = {}
    for key, shape in layout.items():
        if key.endswith("num_batches_tracked"):
            state[key] = torch.tensor(0)
        elif key.endswith("running_var"):
            state[key] = torch.rand(shape, generator=generator) + 0.5
        else:
            state[key] = torch.randn(shape, generator=generator) * 0.05
    return state


@pytest.fixture(scope="session")
def official_checkpoint():
    """official_checkpoint(layout file, variant) -> a random state dict in the authors' layout."""
    return official_state_dict


@pytest.fixture(autouse=True)
def one_torch_thread():
    """The tiny test inputs run faster on one thread; on a busy machine, several threads mostly wait on each other."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
