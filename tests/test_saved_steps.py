"""Steps saved whole (`engine.saved_steps`, `compile_cache.ExecutableStore`): a later process loads them without
tracing, and they compute what the jitted function computes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fmfusion_jax import compile_cache
from fmfusion_jax.engine.saved_steps import saved_step

_SCRIPT = textwrap.dedent(
    """
    import sys
    import numpy as np
    from fmfusion_jax import compile_cache
    from fmfusion_jax.engine.saved_steps import saved_step

    traces = []

    @saved_step(static_argnames=("power",), donate_argnames=("state",))
    def update(state, frame, power):
        traces.append(1)  # runs only while tracing
        return state + frame**power, (state * frame).sum()

    compile_cache.enable_compile_cache(sys.argv[1])
    compile_cache.use_compile_cache()  # as a Mapper starts: the steps of the last process loaded ahead
    state, total = update(np.arange(6.0, dtype=np.float32), np.full(6, 2.0, np.float32), power=3)
    print(len(traces), state.tolist(), float(total))
    """
)


def test_a_later_process_loads_the_step_without_tracing_it(tmp_path):
    folder = tmp_path / "cache"
    script = tmp_path / "step.py"
    script.write_text(_SCRIPT)
    env = {k: v for k, v in os.environ.items() if k != compile_cache.ENV}
    runs = [subprocess.run([sys.executable, str(script), str(folder)], capture_output=True, text=True, env=env) for _ in range(2)]
    for run in runs:
        assert run.returncode == 0, run.stderr
    first, second = (run.stdout.split(" ", 1) for run in runs)
    assert first[0] == "1" and second[0] == "0"  # traced once, by the first process only
    assert first[1] == second[1]
    assert first[1].strip() == f"{[float(x + 8) for x in range(6)]} 30.0"
    (saved,) = folder.glob("fmfusion-update-*.step")
    assert json.loads((folder / compile_cache.ExecutableStore.MANIFEST).read_text())["steps"] == [saved.name]
    # an edit of the step's source: the saved executable is not used, the new code runs
    script.write_text(_SCRIPT.replace("state + frame**power", "state - frame**power"))
    edited = subprocess.run([sys.executable, str(script), str(folder)], capture_output=True, text=True, env=env)
    assert edited.returncode == 0, edited.stderr
    assert edited.stdout.split(" ", 1)[0] == "1"
    assert edited.stdout.split(" ", 1)[1].strip() == f"{[float(x - 8) for x in range(6)]} 30.0"


@pytest.fixture
def store(tmp_path, monkeypatch):
    store = compile_cache.ExecutableStore(tmp_path)
    monkeypatch.setattr(compile_cache, "_STORE", store)
    return store


def _step():
    @saved_step(static_argnames=("scale",))
    def scaled_sum(x, y, scale):
        return (x * scale + y).sum(), x - y

    return scaled_sum


def test_a_saved_step_computes_what_its_jitted_function_computes(store):
    step = _step()
    x, y = jnp.arange(5.0), jnp.ones(5)
    expected = step.__wrapped__(x, y, 3.0)
    got = step(x, y, 3.0)
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
    step(x, y, 3.0)
    step(np.arange(5.0, dtype=np.float32), y, 3.0)  # a host array of the same type: the same executable
    assert step._cache_size() == 1
    np.testing.assert_array_equal(step(x, y, scale=2.0)[0], ((x * 2 + y).sum()))  # another static value: another one
    assert step._cache_size() == 2
    # inside another trace the step is traced into the caller
    np.testing.assert_array_equal(jax.jit(lambda a: step(a, y, 3.0)[0])(x), expected[0])
    assert len(step._executables) == 2  # traced into the caller's executable: none of the step's own


def test_a_damaged_file_is_removed_and_the_step_compiled(store):
    step = _step()
    x, y = jnp.arange(4.0), jnp.ones(4)
    step(x, y, 2.0)
    (saved,) = store.folder.glob("fmfusion-scaled_sum-*.step")
    saved.write_bytes(b"not a step")
    step.clear()
    np.testing.assert_array_equal(step(x, y, 2.0)[0], (x * 2 + y).sum())
    assert not saved.exists() or saved.read_bytes() != b"not a step"  # saved again when compiled anew


def test_without_a_store_the_step_is_its_jitted_function(monkeypatch, tmp_path):
    monkeypatch.setattr(compile_cache, "_STORE", None)
    step = _step()
    step(jnp.arange(3.0), jnp.ones(3), 1.0)
    assert step._cache_size() == 1  # the jit's own entry
    assert not list(tmp_path.iterdir())


def test_the_steps_the_last_process_used_are_loaded_ahead(store, monkeypatch):
    step = _step()
    x, y = jnp.arange(7.0), jnp.ones(7)
    expected = step(x, y, 5.0)
    (saved,) = store.folder.glob("fmfusion-scaled_sum-*.step")
    later = compile_cache.ExecutableStore(store.folder)  # the next process's store
    later.prefetch()
    assert list(later._prefetched) == [saved.name]  # the manifest's steps, being loaded
    monkeypatch.setattr(compile_cache, "_STORE", later)
    step.clear()

    class NotCompiled:
        def lower(self, *args, **kwargs):
            raise AssertionError("loaded ahead: nothing to trace or compile")

    monkeypatch.setattr(step, "_jitted", NotCompiled())
    got = step(x, y, 5.0)
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])
    assert not later._prefetched  # taken


def test_a_step_asked_for_before_its_turn_to_be_loaded_ahead_is_still_loaded(tmp_path, monkeypatch):
    """The loading thread works through the manifest in order; a step taken out of the queue by `load_or_compile`
    while an earlier one is still loading must still get its executable (it waited forever: a hung run)."""
    import threading

    store = compile_cache.ExecutableStore(tmp_path)
    first, second = store.path("first", "key"), store.path("second", "key")
    for path in (first, second):
        path.write_bytes(b"saved")
    manifest = {"code": compile_cache._code_digest(), "steps": [first.name, second.name]}
    (tmp_path / store.MANIFEST).write_text(json.dumps(manifest))
    release = threading.Event()

    def load_step(path):
        if path.name == first.name:
            release.wait(10)  # the first step loads slowly
        return f"executable of {path.name}"

    monkeypatch.setattr(compile_cache, "_load_step", load_step)
    store.prefetch()
    got = []

    def ask():
        got.append(store.load_or_compile("second", "key", lambda: pytest.fail("saved: nothing to compile")))

    asking = threading.Thread(target=ask, daemon=True)
    asking.start()
    for _ in range(1000):  # until the second step is taken out of the queue
        with store._lock:
            if second.name not in store._prefetched:
                break
        asking.join(0.01)
    release.set()
    asking.join(10)
    assert not asking.is_alive(), "load_or_compile waited for a step the loading thread skipped"
    assert got == [f"executable of {second.name}"]


def test_a_second_run_does_not_load_ahead_beside_a_loading_thread_still_at_work(tmp_path, monkeypatch):
    """A run that fails early leaves its loading thread at work; the next run in the same process must not start
    another beside it (two threads deserializing while a third compiled aborted the process in CI)."""
    import threading

    store = compile_cache.ExecutableStore(tmp_path)
    steps = [store.path(name, "key") for name in ("first", "second")]
    for path in steps:
        path.write_bytes(b"saved")
    (tmp_path / store.MANIFEST).write_text(json.dumps({"code": compile_cache._code_digest(), "steps": [p.name for p in steps]}))
    release, loading, most = threading.Event(), [], [0]

    def load_step(path):
        loading.append(path.name)
        most[0] = max(most[0], sum(t.name == "fmfusion-steps" and t.is_alive() for t in threading.enumerate()))
        release.wait(10)
        return f"executable of {path.name}"

    monkeypatch.setattr(compile_cache, "_load_step", load_step)
    store.prefetch()  # the first run
    first_loader = compile_cache._LOADER
    store.forget_prefetched()  # it failed: clear_executables
    next_run = compile_cache.ExecutableStore(tmp_path)  # each command makes a store of its own
    next_run.prefetch()  # while the first run's first step is still loading
    assert compile_cache._LOADER is first_loader and not next_run._prefetched
    release.set()
    first_loader.join(10)
    assert most[0] == 1 and loading == [steps[0].name]  # the second step's future was cancelled: not loaded


def test_saved_steps_are_deserialized_compiled_and_serialized_in_turns(store, monkeypatch):
    """XLA's CPU client is not to deserialize, compile or serialize two saved steps at once (`XLA_TURNS`)."""
    from jax.experimental import serialize_executable

    held = []
    for name in ("serialize", "deserialize_and_load"):
        original = getattr(serialize_executable, name)

        def checked(*args, original=original, name=name):
            held.append((name, compile_cache.XLA_TURNS.locked()))
            return original(*args)

        monkeypatch.setattr(serialize_executable, name, checked)
    step = _step()
    x, y = jnp.arange(6.0), jnp.ones(6)
    compiled = step(x, y, 4.0)  # compiled and saved

    (saved,) = store.folder.glob("fmfusion-scaled_sum-*.step")
    loaded = compile_cache._load_step(saved)
    np.testing.assert_array_equal(loaded(x, y)[0], compiled[0])
    turn_during_compile = []
    store.load_or_compile("other", "key", lambda: turn_during_compile.append(compile_cache.XLA_TURNS.locked()) or loaded)
    assert held and all(locked for _, locked in held) and {name for name, _ in held} == {"serialize", "deserialize_and_load"}
    assert turn_during_compile == [True]
