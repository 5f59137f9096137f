"""Every artefact records the processor and numerical libraries that computed it; its checksum covers
that record, the pipeline's readers ignore it, and fingerprints leave it out."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pandas as pd
import pytest
import scipy
import torch

from latentsim import runtime as rt
from latentsim.fingerprint import compare, fingerprint_tree
from latentsim.checksum import ArtefactError
from latentsim.io import atomic_h5, open_artefact
from latentsim.latent import Autoencoder, LatentIntegrator, RelativeCoordinates, load_autoencoder, save_module
from latentsim.latent.serialization import load_checked
from latentsim.provenance import ENVIRONMENT, environment, machine_signature, main, recorded_environment

ONE_THREAD = True


def h5_artefact(path):
    with atomic_h5(path, config={"dt": 0.1}, seed=3) as f:
        f["x"] = np.arange(4.0)
    return path


def autoencoder_file(path):
    torch.manual_seed(0)
    ae = Autoencoder(12, 3, [16], pca_dim=6)
    save_module(path, ae, extra={"coordinates": "roots"})
    return ae


def runtime_file(path):
    torch.manual_seed(0)
    coords = RelativeCoordinates(12, [0, 6], "roots", root_of=[0] * 6 + [6] * 6)
    ae = Autoencoder(coords.dim, 3, [16], pca_dim=6).eval()
    rt.export_runtime(ae, LatentIntegrator(3, 6, [8]).eval(), coords, path)
    return path


def test_environment_names_this_processor_and_the_running_libraries():
    env = environment()
    assert env["numpy"] == np.__version__ and env["torch"] == torch.__version__ and env["scipy"] == scipy.__version__
    assert env["h5py"] == h5py.__version__ and env["python"] and env["processor"] and env["machine"]
    assert env["torch_threads"] == torch.get_num_threads() and env["torch_blas"]
    assert machine_signature() == f"{env['processor']} | numpy {env['numpy']} | torch {env['torch']}"
    json.dumps(env)  # stored as JSON in HDF5 and .npz files


def test_environment_follows_the_torch_thread_count():
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(n + 1)
        assert environment()["torch_threads"] == n + 1
    finally:
        torch.set_num_threads(n)


def test_hdf5_artefact_records_the_environment_under_its_checksum(tmp_path):
    path = h5_artefact(tmp_path / "a.h5")
    with open_artefact(path) as f:  # the checksum verifies with the environment in it
        env = json.loads(f.attrs[ENVIRONMENT])
        assert f.attrs["seed"] == 3
    assert env["numpy"] == np.__version__ and env["torch"] == torch.__version__
    assert recorded_environment(path) == env


def test_network_round_trips_its_weights_and_records_the_environment(tmp_path):
    path = tmp_path / "autoencoder.pt"
    ae = autoencoder_file(path)
    blob = load_checked(path)  # verified: the checksum covers the environment too
    assert blob[ENVIRONMENT]["torch"] == torch.__version__ and blob[ENVIRONMENT]["numpy"] == np.__version__
    loaded = load_autoencoder(path)
    assert all(torch.equal(loaded.state_dict()[k], v) for k, v in ae.state_dict().items())
    assert recorded_environment(path) == blob[ENVIRONMENT]


def test_runtime_records_the_environment_and_its_readers_ignore_it(tmp_path):
    path = runtime_file(tmp_path / "runtime.npz")
    with np.load(path) as z:
        env = json.loads(str(z[ENVIRONMENT]))
    assert env["numpy"] == np.__version__ and env["torch"] == torch.__version__
    assert ENVIRONMENT not in rt.read_runtime(path)  # verified, and not among the folded arrays
    assert recorded_environment(path) == env


def test_an_altered_environment_fails_the_checksum(tmp_path):
    path = h5_artefact(tmp_path / "a.h5")
    with h5py.File(path, "a") as f:
        f.attrs[ENVIRONMENT] = json.dumps({**json.loads(f.attrs[ENVIRONMENT]), "processor": "another"}, sort_keys=True)
    with pytest.raises(ArtefactError, match="does not match its checksum"):
        with open_artefact(path):
            pass


def test_fingerprints_leave_the_environment_out(tmp_path):
    """The same artefacts recorded on another machine: only the environment differs, and the
    fingerprints compare equal bitwise."""
    here, there = tmp_path / "here", tmp_path / "there"
    for results in (here, there):
        h5_artefact(results / "sim/a.h5")
        autoencoder_file(results / "autoencoder/a/autoencoder.pt")
        runtime_file(results / "rollout/a/runtime.npz")
    other = json.dumps({**environment(), "processor": "another", "torch": "0.0"}, sort_keys=True)
    with h5py.File(there / "sim/a.h5", "a") as f:
        f.attrs[ENVIRONMENT] = other
    blob = torch.load(there / "autoencoder/a/autoencoder.pt", weights_only=True)
    torch.save({**blob, ENVIRONMENT: json.loads(other)}, there / "autoencoder/a/autoencoder.pt")
    with np.load(there / "rollout/a/runtime.npz") as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(there / "rollout/a/runtime.npz", **{**arrays, ENVIRONMENT: np.asarray(other)})
    assert recorded_environment(there / "sim/a.h5")["processor"] == "another"
    a, b = fingerprint_tree(here), fingerprint_tree(there)
    assert len(a) == 3 and not compare(a, b)
    assert not any(ENVIRONMENT in name for entries in a.values() for name in entries)


def test_command_line_prints_the_recorded_environment(tmp_path, capsys):
    path = h5_artefact(tmp_path / "a.h5")
    old = tmp_path / "old.h5"
    with h5py.File(old, "w") as f:
        f["x"] = 1
    assert main([str(path), str(old)]) == 0
    out = capsys.readouterr().out
    assert f'"numpy": "{np.__version__}"' in out and "same processor and libraries as this machine" in out
    assert f"{old}: no environment recorded" in out


def test_fingerprints_leave_wall_times_out_of_tables_and_keep_results(tmp_path):
    """A table's wall-time columns ("ms/step median", "map ms", "train s") may differ between two
    identical runs and are left out; a result column ("error mean") differing is reported."""
    here, there = tmp_path / "here", tmp_path / "there"
    rows = {"method": ["full space", "Neural Modes"], "error mean": [0.0, 0.0048], "ms/step median": [3.2, 10.2],
            "map ms": [np.nan, 1.9], "train s": [0.0, 12.0]}  # fmt: skip
    for results, slower in ((here, 1.0), (there, 6.6)):
        (results / "nm").mkdir(parents=True)
        timed = {k: (np.asarray(v) * slower if k.endswith(("median", "ms", " s")) else v) for k, v in rows.items()}
        pd.DataFrame(timed).to_csv(results / "nm" / "dynamics.csv", index=False)
    assert not compare(fingerprint_tree(here), fingerprint_tree(there))
    pd.DataFrame({**rows, "error mean": [0.0, 0.0049]}).to_csv(there / "nm" / "dynamics.csv", index=False)
    diff = compare(fingerprint_tree(here), fingerprint_tree(there))
    assert len(diff) == 1 and diff[0].startswith("nm/dynamics.csv:row Neural Modes: differs"), diff
