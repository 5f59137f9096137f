"""Artefact integrity: every artefact stores a checksum of its content, every reader checks it, and a
truncated or altered file is caught naming the file, then moved aside so that the next run rewrites it."""

from __future__ import annotations

import logging
import re
import zipfile

import h5py
import numpy as np
import pytest
import torch

from latentsim import runtime as rt
from latentsim.checksum import KEY, ArtefactError
from latentsim.io import atomic_h5, h5_checksum, open_artefact, write_dataset
from latentsim.latent import Autoencoder, LatentIntegrator, RelativeCoordinates, load_autoencoder, load_extra, save_module
from latentsim.latent.serialization import atomic_save, load_checked
from latentsim.neural_modes import load_neural_modes


def corrupt_error(path):
    """pytest.raises for the corrupt-artefact error: names the file, says it was moved aside and what to run."""
    return pytest.raises(ArtefactError, match=rf"^{re.escape(str(path))}: corrupt artefact .*moved aside to {re.escape(str(path))}\.corrupt.*snakemake")


def assert_moved_aside(path):
    assert not path.exists() and path.with_name(path.name + ".corrupt").exists()


def flip_byte(path, offset):
    with open(path, "r+b") as f:
        f.seek(offset)
        b = f.read(1)[0]
        f.seek(offset)
        f.write(bytes([b ^ 0x01]))


def truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


# ----------------------------------------------------------------------------------------- HDF5


def trajectories_like(path, seed=0):
    """A small file in the trajectory layout (root arrays and attributes, a sequence group)."""
    rng = np.random.default_rng(seed)
    with atomic_h5(path, config={"dt": 0.03}, seed=seed) as f:
        write_dataset(f, "rest_positions", rng.random((50, 3)))
        f.attrs["dt"] = 0.03
        g = f.create_group("sequences").create_group("test_mid")
        g.attrs["split"] = "test"
        write_dataset(g, "positions", rng.random((20, 50, 3)))
        write_dataset(g, "frame_ms", rng.random(20))
    return path


def test_h5_checksum_is_recorded_and_a_sound_file_reads(tmp_path):
    path = trajectories_like(tmp_path / "trajectories.h5")
    with h5py.File(path, "r") as f:
        assert f.attrs[KEY] == h5_checksum(f) and len(f.attrs[KEY]) == 64
    with open_artefact(path) as f:
        assert f["sequences/test_mid/positions"].shape == (20, 50, 3)
    assert not (tmp_path / "trajectories.h5.corrupt").exists()


def test_h5_checksum_covers_every_dataset_and_attribute_but_not_layout(tmp_path):
    a, b = trajectories_like(tmp_path / "a.h5"), trajectories_like(tmp_path / "b.h5")
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        assert fa.attrs[KEY] == fb.attrs[KEY]  # same content, same checksum
    c = trajectories_like(tmp_path / "c.h5", seed=1)
    with h5py.File(a, "r") as fa, h5py.File(c, "r") as fc:
        assert fa.attrs[KEY] != fc.attrs[KEY]
    with atomic_h5(tmp_path / "d.h5", config={"dt": 0.03}, seed=0) as f:  # chunked and compressed: the same content
        with h5py.File(a, "r") as fa:
            for name in ("rest_positions", "sequences/test_mid/positions", "sequences/test_mid/frame_ms"):
                f.create_dataset(name, data=fa[name][()], chunks=True, compression="gzip", track_times=False)
            f.attrs["dt"] = 0.03
            f["sequences/test_mid"].attrs["split"] = "test"
            assert h5_checksum(f) == fa.attrs[KEY]


def test_truncated_h5_names_the_file_and_is_moved_aside(tmp_path):
    path = trajectories_like(tmp_path / "trajectories.h5")
    truncate(path)
    with corrupt_error(path) as err:
        with open_artefact(path):
            pass
    assert "truncated" in str(err.value)  # HDF5's own reason is kept
    assert_moved_aside(path)


def test_flipped_byte_in_an_h5_dataset_is_caught(tmp_path):
    path = trajectories_like(tmp_path / "trajectories.h5")
    with h5py.File(path, "r") as f:
        offset = f["sequences/test_mid/positions"].id.get_offset()  # contiguous: the data's first byte in the file
    flip_byte(path, offset + 1000)
    with h5py.File(path, "r") as f:  # HDF5 itself reads it without complaint
        assert np.isfinite(f["sequences/test_mid/positions"][()]).all()
    with corrupt_error(path) as err:
        with open_artefact(path):
            pass
    assert "does not match its checksum" in str(err.value)
    assert_moved_aside(path)


@pytest.mark.parametrize("edit", ["five positions", "attribute", "new dataset"])
def test_an_altered_h5_value_is_caught(tmp_path, edit):
    """Values changed through HDF5 itself (a valid file): five flipped ground-truth positions, a changed
    attribute of a group, an added dataset."""
    path = trajectories_like(tmp_path / "trajectories.h5")
    with h5py.File(path, "r+") as f:
        if edit == "five positions":
            ds = f["sequences/test_mid/positions"]
            x = ds[()]
            x[3, :5, 0] = -x[3, :5, 0]
            ds[...] = x
        elif edit == "attribute":
            f["sequences/test_mid"].attrs["split"] = "train"
        else:
            f["extra"] = np.zeros(3)
    with corrupt_error(path):
        with open_artefact(path):
            pass
    assert_moved_aside(path)


def test_h5_without_a_checksum_reads_with_a_warning(tmp_path, caplog):
    path = tmp_path / "old.h5"
    with h5py.File(path, "w") as f:
        f["x"] = np.arange(3)
    with caplog.at_level(logging.WARNING), open_artefact(path) as f:
        assert f["x"][()].tolist() == [0, 1, 2]
    assert f"{path}: no sha256 checksum" in caplog.text
    assert path.exists()


def test_missing_h5_is_a_missing_file_not_a_corrupt_one(tmp_path):
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / "nothing.h5"))):
        with open_artefact(tmp_path / "nothing.h5"):
            pass


# ----------------------------------------------------------------------------------------- PyTorch


def tensor_offset(path, member_suffix="/data/0"):
    """Byte offset in the file of a tensor record of a torch.save zip (stored uncompressed)."""
    with zipfile.ZipFile(path) as z:
        info = next(i for i in z.infolist() if i.filename.endswith(member_suffix))
    with open(path, "rb") as f:
        f.seek(info.header_offset + 26)
        name_len, extra_len = np.frombuffer(f.read(4), dtype="<u2")
    return info.header_offset + 30 + int(name_len) + int(extra_len), info.file_size


def saved_autoencoder(path):
    torch.manual_seed(0)
    ae = Autoencoder(12, 3, [16], pca_dim=6)
    save_module(path, ae, extra={"coordinates": "roots", "train_seconds": 1.5})
    return ae


def test_weights_round_trip_with_their_checksum(tmp_path):
    path = tmp_path / "autoencoder.pt"
    ae = saved_autoencoder(path)
    assert KEY in torch.load(path, weights_only=True)
    loaded = load_autoencoder(path)
    for k, v in ae.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v)
    assert load_extra(path) == {"coordinates": "roots", "train_seconds": 1.5}


def test_flipped_byte_in_a_weight_is_caught(tmp_path):
    path = tmp_path / "autoencoder.pt"
    saved_autoencoder(path)
    offset, size = tensor_offset(path)
    flip_byte(path, offset + size // 2)
    with corrupt_error(path) as err:
        load_autoencoder(path)
    assert "does not match its checksum" in str(err.value)  # PyTorch itself loads it without complaint
    assert_moved_aside(path)


def test_changed_weight_in_a_valid_file_is_caught(tmp_path):
    """One bit of one decoder weight changed, the file rewritten by torch.save: only the checksum tells."""
    path = tmp_path / "autoencoder.pt"
    saved_autoencoder(path)
    blob = torch.load(path, weights_only=True)
    w = next(v for k, v in blob["state_dict"].items() if v.dtype == torch.float32 and v.numel() > 1)
    w.view(torch.int32).reshape(-1)[0] ^= 1
    torch.save(blob, path)
    with corrupt_error(path) as err:
        load_autoencoder(path)
    assert "does not match its checksum" in str(err.value)


def test_truncated_weights_name_the_file(tmp_path):
    path = tmp_path / "autoencoder.pt"
    saved_autoencoder(path)
    truncate(path)
    with corrupt_error(path):
        load_autoencoder(path)
    assert_moved_aside(path)


def test_every_network_loader_is_checked(tmp_path):
    """The Neural Modes network and the training checkpoint load through the same checked reader."""
    nm = tmp_path / "neural_modes.pt"
    nm.write_bytes(b"PK\x03\x04 not a whole file")
    with corrupt_error(nm):
        load_neural_modes(nm)
    ck = tmp_path / "checkpoint.pt"
    atomic_save({"epoch": 3, "model": {"w": torch.arange(4.0)}, "history": {"loss": [1.0, 0.5]}}, ck)
    assert load_checked(ck)["history"]["loss"] == [1.0, 0.5]
    blob = torch.load(ck, weights_only=True)
    blob["history"]["loss"][1] = 0.25
    torch.save(blob, ck)
    with corrupt_error(ck):
        load_checked(ck)


def test_weights_without_a_checksum_load_with_a_warning(tmp_path, caplog):
    path = tmp_path / "old.pt"
    ae = Autoencoder(12, 3, [16], pca_dim=6)
    torch.save({"kind": "Autoencoder", "hparams": ae.hparams, "state_dict": ae.state_dict(), "extra": {}}, path)
    with caplog.at_level(logging.WARNING):
        load_autoencoder(path)
    assert f"{path}: no sha256 checksum" in caplog.text


# ----------------------------------------------------------------------------------------- runtime.npz


def runtime_file(path):
    torch.manual_seed(0)
    coords = RelativeCoordinates(12, [0, 6], "roots", root_of=[0] * 6 + [6] * 6)
    ae = Autoencoder(coords.dim, 3, [16], pca_dim=6).eval()
    integ = LatentIntegrator(3, 6, [8]).eval()
    rt.export_runtime(ae, integ, coords, path)
    return path


def test_runtime_file_round_trips_with_its_checksum(tmp_path):
    path = runtime_file(tmp_path / "runtime.npz")
    with np.load(path) as z:
        assert KEY in z.files
    folded = rt.read_runtime(path)
    assert KEY not in folded and folded["header"]["version"] == rt.VERSION


def test_flipped_byte_in_runtime_npz_is_caught(tmp_path):
    path = runtime_file(tmp_path / "runtime.npz")
    offset, size = tensor_offset(path, "dec_Wout.npy")
    flip_byte(path, offset + size - 5)  # in the array data, past the .npy header
    with corrupt_error(path):
        rt.load(path)
    assert_moved_aside(path)


def test_changed_array_in_a_valid_runtime_npz_is_caught(tmp_path):
    path = runtime_file(tmp_path / "runtime.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["dec_Wout"] = arrays["dec_Wout"].copy()
    arrays["dec_Wout"][0, 0] += 1e-12
    np.savez(path, **arrays)
    with corrupt_error(path) as err:
        rt.load_runtime(path)
    assert "does not match its checksum" in str(err.value)


def test_truncated_runtime_npz_names_the_file(tmp_path):
    path = runtime_file(tmp_path / "runtime.npz")
    truncate(path)
    with corrupt_error(path):
        rt.read_runtime(path)
    assert_moved_aside(path)


def test_a_csv_table_is_checked_against_its_checksum_file(tmp_path, caplog):
    """metrics.csv with rows removed, or cut mid-row, is named and moved aside (with its checksum file) instead of
    read as a smaller table; a table without a checksum file reads with a warning."""
    import pandas as pd

    from latentsim.io import read_csv
    from latentsim.report.tables import write_table

    path = tmp_path / "metrics.csv"
    df = pd.DataFrame({"method": ["a", "b", "c"], "seed": [0, 1, 2], "mean_error": [0.1, 0.2, 0.3]})
    write_table(df, path)
    assert (tmp_path / "metrics.csv.sha256").is_file()
    assert read_csv(path).equals(df)
    for damage in (lambda text: "\n".join(text.splitlines()[:2]) + "\n", lambda text: text[: len(text) - 5]):
        path.write_text(damage(path.read_text()))
        with pytest.raises(ArtefactError, match=r"metrics\.csv: corrupt artefact \(its bytes do not match its checksum in metrics\.csv\.sha256"):
            read_csv(path)
        assert not path.exists() and (tmp_path / "metrics.csv.corrupt").exists() and not (tmp_path / "metrics.csv.sha256").exists()
        write_table(df, path)
    (tmp_path / "metrics.csv.sha256").unlink()
    with caplog.at_level(logging.WARNING):
        assert read_csv(path).equals(df)
    assert "no sha256 checksum" in caplog.text
    path.write_bytes(b"\x00\xff\xfe binary")
    with pytest.raises(ArtefactError, match=r"pandas cannot read it as CSV"):
        read_csv(path)
