"""train/run.py, or a user's script calling gymnasium.make_vec, made small and held in one phase, for
tests/test_signals_phases.py (a real signal at each phase of a run).

    python tests/phase_driver.py MARKER HOLD run ARGS...   # train/run.py ARGS (its __main__ path)
    python tests/phase_driver.py MARKER HOLD gym ID CACHE   # gymnasium.make_vec(ID, num_envs=2, cache_dir=CACHE)

HOLD names the phase to stop in (record, collect, fit, vae, start, final_eval, prior_eval): on entering it,
at a point where its work is under way (record: inside the episodes; collect: frames written; vae: in
the second epoch), the driver writes MARKER, then repeats that step's own work (the real function,
again and again) until a signal stops it, so that the signal lands in the phase whatever the
machine's load and however short the phase (fitting the prior takes a second). `none` holds
nothing: the test watches the run directory instead.

VKGRL_TEST_VISION="RESOLUTION,IMAGES,EPOCHS" replaces the quick vision preset by a tiny one (the same
settings otherwise), so that the vision prerequisites take seconds.
"""

import os
import runpy
import signal
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
MAX_HOLD_S = 600.0  # a signal that never comes: the phase ends normally (the test's own limit fails it)


def tiny_vision_preset(spec: str):
    """The quick preset at RESOLUTION px, IMAGES images, EPOCHS epochs (tests compute its cache paths with it)."""
    import dataclasses

    from vkgrl_newton.prepare.vision import VISION_PRESETS

    resolution, images, epochs = (int(v) for v in spec.split(","))
    return dataclasses.replace(VISION_PRESETS["quick"], resolution=resolution, num_images=images, vae_epochs=epochs,
                               vae_batch_size=16, val_fraction=0.25, episode_steps=12)


def held(real, marker: Path, when=lambda *a, **kw: True, skip: int = 0):
    """`real`, except that the first call for which when(...) holds, after `skip` such calls, writes
    `marker` and repeats `real` until a stop signal interrupts it (at most MAX_HOLD_S)."""
    state = {"done": False, "seen": 0}

    def wrapper(*args, **kwargs):
        if state["done"] or not when(*args, **kwargs):
            return real(*args, **kwargs)
        state["seen"] += 1
        if state["seen"] <= skip:
            return real(*args, **kwargs)
        state["done"] = True
        marker.write_text(real.__name__)
        deadline = time.monotonic() + MAX_HOLD_S
        result = real(*args, **kwargs)
        while time.monotonic() < deadline:
            result = real(*args, **kwargs)
        return result

    return wrapper


def install_hold(hold: str, marker: Path) -> None:
    if hold == "record":  # the demonstrator's pose, read after each control step: inside the episodes
        from vkgrl_newton.envs import demonstrations

        demonstrations._eta = held(demonstrations._eta, marker, skip=2)
    elif hold == "collect":  # the privileged state stored beside each rendered frame: part of a set written
        from vkgrl_newton.prepare import images

        images.relative_target_state = held(images.relative_target_state, marker)
    elif hold == "fit":
        from vkgrl_newton.kmp import prior

        prior.fit_prior = held(prior.fit_prior, marker)
    elif hold == "vae":  # once the first epoch is checkpointed: inside the second
        from vkgrl_newton.vision import train as vae_train

        checkpointed = []
        real_save = vae_train.save_vae

        def save_vae(path, *args, **kwargs):
            out = real_save(path, *args, **kwargs)
            checkpointed.append(Path(path).name == vae_train.CHECKPOINT.name)
            return out

        vae_train.save_vae = save_vae
        vae_train._read_batch = held(vae_train._read_batch, marker, when=lambda *a, **kw: any(checkpointed))
    elif hold == "start":  # the run's files written, its loop not yet begun (inside train's _make_loop)
        from vkgrl_newton.run import train

        train.build_rollout_policy = held(train.build_rollout_policy, marker)
    elif hold in ("final_eval", "prior_eval"):  # envs.evaluation.evaluate, by the progress bar's name
        from vkgrl_newton.envs import evaluation

        desc = "final evaluation" if hold == "final_eval" else "the prior, same episodes"
        evaluation.evaluate = held(evaluation.evaluate, marker, when=lambda *a, **kw: kw.get("desc") == desc)
    elif hold != "none":
        raise SystemExit(f"phase_driver: unknown hold {hold!r}")


def main() -> None:
    # Ctrl-C's KeyboardInterrupt, whatever this process inherited: a background job of a non-interactive shell
    # (`cmd &` in a CI script) starts with SIGINT ignored, and Python then installs no handler of its own, so the
    # tests' SIGINT would be lost and the held phase would run on
    signal.signal(signal.SIGINT, signal.default_int_handler)
    marker, hold, mode, *rest = sys.argv[1:]
    if spec := os.environ.get("VKGRL_TEST_VISION"):
        from vkgrl_newton.prepare import vision

        vision.VISION_PRESETS["quick"] = tiny_vision_preset(spec)
    install_hold(hold, Path(marker))
    if mode == "run":
        sys.argv = [str(ROOT / "train" / "run.py"), *rest]
        runpy.run_path(sys.argv[0], run_name="__main__")  # exits with run.py's code
    elif mode == "gym":  # a user's script: no handler of its own
        import gymnasium

        import vkgrl_newton  # noqa: F401  (registers the ids)

        env_id, cache_dir = rest
        gymnasium.make_vec(env_id, num_envs=2, device="cpu", cache_dir=cache_dir).close()
        print("made")
    else:
        raise SystemExit(f"phase_driver: unknown mode {mode!r}")


if __name__ == "__main__":
    main()
