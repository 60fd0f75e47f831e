"""A saved fit (fit_state.h5) edited or crafted with its fit id written again (a hash of its content: anyone
can): its store attribute and fit id check out, so it was loaded as it was. dense-vlad's 64-wide centres
then discarded the good stores and failed the run, every time, without naming the file ('Vocabulary
dimension 64 does not match feature dimension 128'); bytes or a 1-d array were a traceback; 16 centres
where 8 are fitted were used silently. Now the method refuses it, the file is discarded (said) and fitted again."""
import h5py
import numpy as np
import pytest

import vprbench
from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError
from vprbench.store.folder import fit_id_of
from runs import evaluate_method as evaluate
from store_helpers import Fitted


class Checked(Fitted):
    """Fitted, whose load_fit_state refuses a centre of another length (as dense-vlad's and anyloc's do)."""

    def load_fit_state(self, state):
        centre = np.asarray(state["centre"])
        if centre.shape != (self.size * self.size,):
            raise ValueError(f"a centre of shape {centre.shape}, not ({self.size * self.size},)")
        self.centre = centre.astype(np.float32)


@pytest.fixture(scope="module", autouse=True)
def checked_method():
    from vprbench.methods.registry import available_methods

    if "checked-fit-test" not in available_methods():
        vprbench.register_method("checked-fit-test", Checked)


def rewritten(path, state: dict) -> None:
    """`path` holding `state` with a fit id and store attribute that check out, as a crafted copy would."""
    with h5py.File(path, "r") as f:
        store = f.attrs["store"]
    with h5py.File(path, "w") as f:
        group = f.create_group("state")
        for key, value in state.items():
            group.create_dataset(key, data=value)
        f.attrs["fit_id"], f.attrs["store"] = fit_id_of(state), store


def test_a_fit_state_the_method_refuses_is_discarded_and_fitted_again(shared_data, tmp_path):
    dataset = load_dataset("corridor", shared_data)
    first = evaluate(vprbench.create_method("checked-fit-test"), dataset, cache_dir=tmp_path)
    path = next(tmp_path.rglob("fit_state.h5"))
    with h5py.File(path, "r") as f:
        fitted = f["state"]["centre"][...]
    rewritten(path, {"centre": np.ones(10, np.float32)})
    with pytest.warns(UserWarning, match=r"Discarding \S+fit_state\.h5: the method refuses it \(a centre of shape "
                                         r"\(10,\), not \(64,\)\); it is recomputed\."):
        again = evaluate(vprbench.create_method("checked-fit-test"), dataset, cache_dir=tmp_path)
    # fitted again as before: the stores of that fit were kept, the results are the first run's
    assert again["descriptors_computed"] == {"database": 0, "queries": 0}
    assert again["recall"] == first["recall"]
    with h5py.File(path, "r") as f:
        assert np.array_equal(f["state"]["centre"][...], fitted)


@pytest.mark.parametrize("centres, said", [
    (np.ones((8, 64), np.float32), r"float32 \(8, 64\), not 8 x 128 finite numbers"),
    (np.ones((16, 128), np.float32), r"float32 \(16, 128\), not 8 x 128"),
    (np.ones(128, np.float32), r"float32 \(128,\), not 8 x 128"),
    (np.array([b"abc"]), r"\|S3 \(1,\), not 8 x 128"),
    (np.full((8, 128), np.nan, np.float32), r"float32 \(8, 128\) with NaN or infinite values, not 8 x 128"),
])
def test_dense_vlad_refuses_centres_it_does_not_fit(centres, said):
    method = vprbench.create_method("dense-vlad", clusters=8)
    with pytest.raises(VPRBenchError, match=rf"^dense-vlad: the fit state holds centres of {said}"):
        method.load_fit_state({"centres": centres})
    with pytest.raises(VPRBenchError, match=r"^dense-vlad: the fit state holds no centres \(it holds 'other'\)"):
        method.load_fit_state({"other": np.ones((8, 128), np.float32)})
    assert method.centres is None
    method.load_fit_state({"centres": np.ones((8, 128), np.float64)})  # what it fits: read as float32
    assert method.centres.dtype == np.float32 and method.centres.shape == (8, 128)


def test_anyloc_refuses_centres_other_than_its_facets_width():
    method = vprbench.create_method("anyloc", backbone="dinov2_vits14", weights="random", layer=1, aggregation="vlad",
                                    clusters=4, vocabulary="map")
    with pytest.raises(VPRBenchError, match=r"^anyloc: the fit state holds centres of float32 \(4, 64\), not 4 x 384"):
        method.load_fit_state({"centres": np.ones((4, 64), np.float32)})
    method.load_fit_state({"centres": np.ones((4, 384), np.float32)})
    assert tuple(method.centres.shape) == (4, 384)
