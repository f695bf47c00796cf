"""Trust on disk (anm_torchrl.artifacts): corrupted, crafted, half-written and raced artifacts never load silently."""

import json
import os
import pickle
import signal
import subprocess
import sys
import textwrap

import pytest
import torch

from anm_torchrl import artifacts as A

KIND = "anm_torchrl.test"


def _tensors():
    return {"w": torch.arange(12, dtype=torch.float32).reshape(3, 4), "b": torch.ones(4, dtype=torch.float64),
            "n": torch.tensor([1, 2, 3])}


def _flip(path, offset, n=4):
    data = bytearray(path.read_bytes())
    for i in range(offset, offset + n):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def _run(code, tmp_path):
    """Run ``code`` in a child Python (it may SIGKILL itself); returns the exit code."""
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=tmp_path, timeout=120).returncode


# --------------------------------------------------------------------------------------------- tensors
def test_tensors_round_trip(tmp_path):
    f = A.save_tensors(tmp_path / "m.safetensors", _tensors(), {"arch": [3, 4], "note": "x"}, KIND)
    got, meta = A.load_tensors(f, KIND)
    assert meta == {"arch": [3, 4], "note": "x"}
    umask = os.umask(0)
    os.umask(umask)
    assert f.stat().st_mode & 0o777 == 0o666 & ~umask  # safetensors alone would create it 0600
    for k, v in _tensors().items():
        assert torch.equal(got[k], v) and got[k].dtype == v.dtype


def test_flipped_bytes_in_weights_raise_naming_the_file(tmp_path):
    f = A.save_tensors(tmp_path / "m.safetensors", _tensors(), {}, KIND)
    _flip(f, f.stat().st_size - 8)  # inside the last tensor's data
    with pytest.raises(A.ArtifactError, match=r"m\.safetensors is corrupted: content hash"):
        A.load_tensors(f, KIND)


def test_flipped_bytes_in_header_raise_naming_the_file(tmp_path):
    f = A.save_tensors(tmp_path / "m.safetensors", _tensors(), {}, KIND)
    _flip(f, 20)  # inside the JSON header
    with pytest.raises(A.ArtifactError, match=r"m\.safetensors"):
        A.load_tensors(f, KIND)


def test_wrong_kind_and_foreign_files_raise(tmp_path):
    f = A.save_tensors(tmp_path / "m.safetensors", _tensors(), {}, KIND)
    with pytest.raises(A.ArtifactError, match="holds a 'anm_torchrl.test' artifact, expected 'other'"):
        A.load_tensors(f, "other")
    txt = tmp_path / "t.safetensors"
    txt.write_text("hello, I am not a tensor file")
    with pytest.raises(A.ArtifactError, match=r"t\.safetensors is not a readable safetensors file"):
        A.load_tensors(txt, KIND)
    from safetensors.torch import save_file

    plain = tmp_path / "plain.safetensors"
    save_file(_tensors(), str(plain))
    with pytest.raises(A.ArtifactError, match="not an anm_torchrl artifact"):
        A.load_tensors(plain, KIND)
    with pytest.raises(A.ArtifactError, match="no such file"):
        A.load_tensors(tmp_path / "missing.safetensors", KIND)


def test_nan_weight_is_refused_at_save_and_at_load(tmp_path):
    bad = _tensors()
    bad["w"][1, 2] = float("nan")
    with pytest.raises(A.ArtifactError, match="tensor 'w'.*NaN or inf"):
        A.save_tensors(tmp_path / "nan.safetensors", bad, {}, KIND)
    assert not list(tmp_path.iterdir())  # nothing written
    # A file whose hash is right but which holds a NaN (written by a buggy or older saver) is still refused.
    from safetensors.torch import save_file

    header = {"format": A.FORMAT, "format_version": A.FORMAT_VERSION, "kind": KIND, "metadata": {}}
    f = tmp_path / "nan2.safetensors"
    save_file(bad, str(f), metadata={"anm_torchrl": json.dumps(header, sort_keys=True),
                                     "sha256": A.tensors_sha256(bad, header)})
    with pytest.raises(A.ArtifactError, match=r"nan2\.safetensors is corrupted: tensor 'w'.*NaN"):
        A.load_tensors(f, KIND)


# --------------------------------------------------------------------------------------------- manifests
class _Evil:
    """Unpickling this creates the file ``PWNED`` in the working folder."""

    def __reduce__(self):
        return (open, ("PWNED", "w"))


def _load_pickle_folder(folder):
    """What a loader does: verify the manifest, then (only then) unpickle."""
    A.verify_manifest(folder, KIND)
    return pickle.loads((folder / "model.pkl").read_bytes())


def _save_folder(path, payload=b"", overwrite=False):
    with A.atomic_folder(path, overwrite=overwrite) as tmp:
        (tmp / "model.pkl").write_bytes(pickle.dumps({"coef": [1.0, 2.0]}))
        (tmp / "sub").mkdir()
        (tmp / "sub" / "extra.bin").write_bytes(b"abc" + payload)
        A.write_manifest(tmp, KIND, {"rows": 10})
    return path


def test_manifest_round_trip_and_corruption(tmp_path):
    d = _save_folder(tmp_path / "reg")
    assert A.verify_manifest(d, KIND) == {"rows": 10}
    assert _load_pickle_folder(d) == {"coef": [1.0, 2.0]}
    _flip(d / "sub" / "extra.bin", 0, n=3)
    with pytest.raises(A.ArtifactError, match=r"extra\.bin is corrupted: sha256"):
        A.verify_manifest(d, KIND)
    with pytest.raises(A.ArtifactError, match="expected 'other'"):
        A.verify_manifest(_save_folder(tmp_path / "reg2"), "other")
    (tmp_path / "reg2" / "planted.joblib").write_bytes(b"x")
    with pytest.raises(A.ArtifactError, match="does not list.*planted.joblib"):
        A.verify_manifest(tmp_path / "reg2", KIND)
    (tmp_path / "nomanifest").mkdir()
    with pytest.raises(A.ArtifactError, match="has no manifest.json"):
        A.verify_manifest(tmp_path / "nomanifest", KIND)


def test_crafted_pickle_is_never_unpickled(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    d = _save_folder(tmp_path / "reg")
    (d / "model.pkl").write_bytes(pickle.dumps(_Evil()))
    with pytest.raises(A.ArtifactError, match=r"model\.pkl is corrupted"):
        _load_pickle_folder(d)
    assert not (tmp_path / "PWNED").exists()
    pickle.loads((d / "model.pkl").read_bytes()).close()  # the crafted file does run code when unpickled unchecked
    assert (tmp_path / "PWNED").exists()


# --------------------------------------------------------------------------------------------- atomicity
def test_atomic_folder_failure_keeps_previous_and_leaves_nothing(tmp_path):
    d = _save_folder(tmp_path / "reg")
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(RuntimeError, match="boom"):
        with A.atomic_folder(d, overwrite=True) as tmp:
            (tmp / "model.pkl").write_bytes(b"half")
            raise RuntimeError("boom")
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert _load_pickle_folder(d) == {"coef": [1.0, 2.0]}
    with pytest.raises(FileExistsError, match="overwrite"):
        _save_folder(d)
    _save_folder(d, payload=b"new", overwrite=True)
    assert (d / "sub" / "extra.bin").read_bytes() == b"abcnew"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["reg"]


def test_killed_folder_save_leaves_no_artifact_and_is_cleaned(tmp_path):
    rc = _run("""
        import os, signal
        from anm_torchrl import artifacts as A
        with A.atomic_folder("reg") as tmp:
            (tmp / "model.pkl").write_bytes(b"x" * 1000)
            os.kill(os.getpid(), signal.SIGKILL)
        """, tmp_path)
    assert rc == -signal.SIGKILL
    assert not (tmp_path / "reg").exists()
    assert [p.name.startswith(".reg.tmp-") for p in tmp_path.iterdir()] == [True]  # the killed save's temp
    with pytest.raises(A.ArtifactError, match="no such artifact folder"):
        A.verify_manifest(tmp_path / "reg", KIND)  # the next load cleans the dead writer's temp up
    assert list(tmp_path.iterdir()) == []


def test_killed_file_save_keeps_previous_and_is_cleaned(tmp_path):
    f = A.save_tensors(tmp_path / "m.safetensors", _tensors(), {}, KIND)
    rc = _run("""
        import os, signal
        from anm_torchrl import artifacts as A
        def write(tmp):
            tmp.write_bytes(b"partial")
            os.kill(os.getpid(), signal.SIGKILL)
        A.atomic_write("m.safetensors", write)
        """, tmp_path)
    assert rc == -signal.SIGKILL
    assert len(list(tmp_path.iterdir())) == 2
    A.load_tensors(f, KIND)  # previous file intact; the stale temp removed
    assert [p.name for p in tmp_path.iterdir()] == ["m.safetensors"]


def test_live_writers_temp_is_not_removed(tmp_path):
    live = A._tmp_name(tmp_path / "reg", "tmp")  # named after this (live) process
    live.mkdir()
    assert A.clean_stale(tmp_path / "reg") == [] and live.exists()


# --------------------------------------------------------------------------------------------- locking
def test_two_writers_one_fails_clearly(tmp_path):
    target = tmp_path / "data"
    with A.exclusive_lock(target):
        with pytest.raises(A.LockedError, match=rf"data is being written by another process.*pid {os.getpid()}"):
            with A.exclusive_lock(target):
                pass
    with A.exclusive_lock(target):  # released on exit
        pass
    assert list(tmp_path.iterdir()) == []


def test_two_processes_one_fails(tmp_path):
    """A child holds the lock while the parent tries; then a killed holder's stale lock is broken."""
    child = subprocess.Popen([sys.executable, "-c", textwrap.dedent("""
        import sys, time
        from anm_torchrl import artifacts as A
        with A.exclusive_lock("data"):
            print("locked", flush=True)
            time.sleep(60)
        """)], cwd=tmp_path, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "locked"
        with pytest.raises(A.LockedError, match=f"pid {child.pid}"):
            with A.exclusive_lock(tmp_path / "data"):
                pass
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
        child.stdout.close()
    with A.exclusive_lock(tmp_path / "data"):  # the holder is dead: its lock is stale
        assert json.loads((tmp_path / ".data.lock").read_text())["pid"] == os.getpid()


def test_atomic_folder_replaces_only_an_artifact_of_its_kind(tmp_path):
    """With ``kind``, overwrite replaces a folder saved as that kind of artifact (damaged or not), never a user's
    file or folder given by mistake (``train_surrogate.py surrogate.path=<a file>`` deleted it)."""
    victim = tmp_path / "notes.txt"
    victim.write_text("precious")
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "thesis.txt").write_text("x")
    for path, what in ((victim, "is a file"), (docs, "is a folder that is not a saved 'test.kind' artifact")):
        with pytest.raises(FileExistsError, match=what):
            with A.atomic_folder(path, overwrite=True, kind="test.kind") as tmp:
                (tmp / "a").write_text("new")
    assert victim.read_text() == "precious" and (docs / "thesis.txt").read_text() == "x"
    art = tmp_path / "art"
    art.mkdir()  # an empty folder holds nothing to lose: replaced
    for payload in ("old", "new"):
        with A.atomic_folder(art, overwrite=True, kind="test.kind") as tmp:
            (tmp / "a").write_text(payload)
            A.write_manifest(tmp, "test.kind")
    assert (art / "a").read_text() == "new"
    with pytest.raises(FileExistsError, match="not a saved 'other.kind' artifact"):
        with A.atomic_folder(art, overwrite=True, kind="other.kind"):
            pass
