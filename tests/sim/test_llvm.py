"""libLLVM discovery: version parsing, the environment override, and the message when none exists."""

from __future__ import annotations

import pytest

from sim.projection import llvm


def test_version_is_read_from_versioned_names(tmp_path):
    for name, major in [("libLLVM-19.so", 19), ("libLLVM.so.18.1", 18), ("libLLVM-16.so.1", 16),
                        ("libLLVM-15.so.1", 15)]:
        p = tmp_path / name
        p.write_bytes(b"")
        assert llvm._major_from_name(p) == major


def test_environment_override_is_honoured_and_checked(tmp_path, monkeypatch):
    lib = tmp_path / "libLLVM-17.so"
    lib.write_bytes(b"")
    monkeypatch.setenv(llvm.ENV_VAR, str(lib))
    found = llvm.find()
    assert found.path == lib and found.major == 17 and found.source == "environment"
    monkeypatch.setenv(llvm.ENV_VAR, str(tmp_path / "missing.so"))
    with pytest.raises(llvm.LLVMNotFoundError, match="does not name an existing file"):
        llvm.find()
    old = tmp_path / "libLLVM-15.so"
    old.write_bytes(b"")
    monkeypatch.setenv(llvm.ENV_VAR, str(old))
    with pytest.raises(llvm.LLVMNotFoundError, match="LLVM 15"):
        llvm.find()


def test_no_llvm_says_what_to_install(monkeypatch):
    monkeypatch.delenv(llvm.ENV_VAR, raising=False)
    monkeypatch.setattr(llvm, "candidates", lambda: [])
    with pytest.raises(llvm.LLVMNotFoundError) as e:
        llvm.find()
    assert "apt-get install libllvm19" in str(e.value) and llvm.ENV_VAR in str(e.value)


def test_search_skips_llvm_older_than_16(tmp_path, monkeypatch):
    for name in ("libLLVM-15.so.1", "libLLVM-14.so", "libLLVM-19.so.1", "libLLVM-17.so"):
        (tmp_path / name).write_bytes(b"")
    monkeypatch.setattr(llvm, "_SEARCH_DIRS", (str(tmp_path),))
    monkeypatch.setattr(llvm.glob, "glob", _only_under(tmp_path, llvm.glob.glob))
    majors = [c.major for c in llvm.candidates()]
    assert majors == [19, 17]


def _only_under(root, glob_fn):
    def wrapped(pattern):
        return glob_fn(pattern) if pattern.startswith(str(root)) else []
    return wrapped


def test_the_running_dr_jit_uses_llvm_16_or_newer():
    import drjit as dr

    from sim.projection.backend import ensure_variant

    if ensure_variant().startswith("llvm"):
        assert dr.detail.llvm_version()[0] >= llvm.MIN_LLVM_MAJOR
