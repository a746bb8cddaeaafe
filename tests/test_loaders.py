"""simloader.loaders.StatefulDataLoader: torchdata's loader, whose load_state_dict refuses by
name a state saved with another number of workers (torchdata's own fails at the next
iteration with a bare AssertionError), over a map-style dataset, a store's transitions and a
Mixture; a state of the same count resumes as torchdata's does."""

import subprocess
import sys

import pytest
import torch

pytest.importorskip("torchdata")

import simloader  # noqa: E402
from simloader import controls  # noqa: E402
from simloader.loaders import StatefulDataLoader  # noqa: E402


class Numbers(torch.utils.data.Dataset):
    def __len__(self):
        return 12

    def __getitem__(self, i):
        return torch.tensor(i)


def saved_after(loader, batches, read=torch.Tensor.tolist):
    """The loader's state after `batches` batches, and the batches it delivers next (each
    `read`)."""
    it = iter(loader)
    for _ in range(batches):
        next(it)
    state = loader.state_dict()
    return state, [read(b) for b in it]


def refusal(saved, here):
    return (rf"load_state_dict: the state was saved by a loader with num_workers={saved}, this "
            rf"loader has num_workers={here}; each worker's place is saved apart, so make the "
            rf"loader with num_workers={saved} as when saved \(the other arguments too\) to "
            rf"resume")


@pytest.mark.parametrize("saved, here", [(2, 0), (2, 1), (1, 2), (0, 2)])
def test_a_state_of_another_worker_count_is_refused_when_loaded(saved, here):
    state, _ = saved_after(StatefulDataLoader(Numbers(), batch_size=2, num_workers=saved), 2)
    loader = StatefulDataLoader(Numbers(), batch_size=2, num_workers=here)
    with pytest.raises(ValueError, match=refusal(saved, here)):
        loader.load_state_dict(state)
    assert [b.tolist() for b in loader][0] == [0, 1]  # refused: nothing was loaded


@pytest.mark.parametrize("workers", [0, 2])
def test_a_state_of_the_same_worker_count_resumes(workers):
    state, rest = saved_after(StatefulDataLoader(Numbers(), batch_size=2,
                                                 num_workers=workers), 2)
    loader = StatefulDataLoader(Numbers(), batch_size=2, num_workers=workers)
    loader.load_state_dict(state)
    assert [b.tolist() for b in loader] == rest == [[4, 5], [6, 7], [8, 9], [10, 11]]
    loader.load_state_dict({})  # torchdata's "nothing to resume"


def test_what_is_no_loaders_state_is_refused():
    with pytest.raises(ValueError, match=r"load_state_dict: expected a StatefulDataLoader's "
                                         r"state_dict\(\), got a dict of keys \['position'\]"):
        StatefulDataLoader(Numbers(), batch_size=2).load_state_dict({"position": 3})


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    ds = simloader.SimDataset("cartpole", backend="cpu", nbatch=4, nstep=6, nthread=1, seed=0,
                              control=controls.Uniform())
    return simloader.write(ds, tmp_path_factory.mktemp("loaders") / "s.zarr", batches=2,
                           progress=False)


def transitions_loader(store, workers):
    """The loader `Transitions.loader` makes, as simloader's loader."""
    made = simloader.StoredDataset(store).transitions().loader(8, seed=0)
    return StatefulDataLoader(made.dataset, batch_size=None, sampler=made.sampler,
                              num_workers=workers)


def test_a_transitions_state_resumes_with_its_worker_count_and_only_with_it(store):
    state, rest = saved_after(transitions_loader(store, 2), 2, lambda b: b["state"].tolist())
    assert rest
    for here in (0, 1):
        with pytest.raises(ValueError, match=refusal(2, here)):
            transitions_loader(store, here).load_state_dict(state)
    resumed = transitions_loader(store, 2)
    resumed.load_state_dict(state)
    assert [b["state"].tolist() for b in resumed] == rest


def test_a_mixtures_state_is_refused_in_a_loader_of_another_worker_count():
    def mixture():
        return simloader.Mixture([simloader.SimDataset(
            "cartpole", backend="cpu", nbatch=2, nstep=3, nthread=1, seed=i,
            control=controls.Uniform()) for i in range(2)], seed=1)

    loader = StatefulDataLoader(mixture(), batch_size=None, num_workers=2)
    it = iter(loader)
    next(it), next(it), next(it)
    state = loader.state_dict()
    del it
    for here in (0, 1):
        with pytest.raises(ValueError, match=refusal(2, here)):
            StatefulDataLoader(mixture(), batch_size=None, num_workers=here).load_state_dict(
                state)


def test_without_torchdata_it_is_torchs_loader():
    # a process where torchdata cannot be imported
    code = ("import sys; sys.modules['torchdata'] = None\n"
            "import torch\n"
            "from simloader.loaders import StatefulDataLoader\n"
            "assert StatefulDataLoader is torch.utils.data.DataLoader\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
