"""One 'run' preparing a cache entry, for tests/test_cache.py (started twice at once, as two processes).

    python tests/cache_worker.py prior|vision CACHE_DIR CALLS_LOG

The expensive step (recording demonstrations; collecting images and training the VAE) is a stand-in
that appends a line to CALLS_LOG and holds the entry's lock until the other process has said it is
waiting for it (CALLS_LOG + ".waiting", written by the cache's "waiting for another run" log line),
so the two overlap whatever the machine's load: a fixed sleep let the first finish before the second
had imported torch. Everything around it (paths, locks, the KMP fit, the VAE load) is the real code.
"""

import sys
import time
from pathlib import Path

kind, cache_dir, calls = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
waiting = calls.with_name(calls.name + ".waiting")
MAX_HOLD_S = 180.0  # then give up holding: the test's assertion on "waiting" says what went wrong


def log(line: str) -> None:
    print(line, flush=True)
    if line.startswith("waiting for another run"):
        with open(waiting, "a") as f:
            f.write(line + "\n")


def note(what: str) -> None:
    with open(calls, "a") as f:
        f.write(what + "\n")
    t = time.monotonic()
    while not waiting.exists() and time.monotonic() - t < MAX_HOLD_S:
        time.sleep(0.05)


if kind == "prior":
    from vkgrl_newton.prepare import prior as kgrl
    from vkgrl_newton.kmp.demos import synthetic_demos

    def record(task, path, num_demos, *args):
        note("record")
        path.parent.mkdir(parents=True, exist_ok=True)
        synthetic_demos(task, num_demos, action_dim=6, seed=1).save(path)

    kgrl._record_scripted = record
    tables, path = kgrl.load_or_make_prior("PegInsert", 4, cache_dir, num_demos=4, log=log)
    print("RESULT", path, float(abs(tables.mean).sum()))
else:
    from vkgrl_newton.prepare import vision as pipeline
    from vkgrl_newton.vision.vae import DenoisingVAE, VAEConfig, save_vae

    preset = pipeline.VisionPreset(resolution=32, num_images=8, vae_epochs=1)

    def collect(config, out_dir, **kw):
        note("collect")
        out_dir.mkdir(parents=True)
        (out_dir / "meta.json").write_text("{}")

    def train(image_dir, out_dir, **kw):
        note("train")
        cfg = VAEConfig(resolution=32, channels=(8, 8, 8, 8, 8))
        save_vae(out_dir / "vae.pt", DenoisingVAE(cfg), cfg, meta={"task": "PegInsert"})
        (out_dir / "metrics.json").write_text("{}")

    pipeline.collect_images, pipeline.train_vae = collect, train
    encoder, info = pipeline.load_or_make_encoder("PegInsert", preset, cache_dir, "cpu", log=log, progress=False)
    print("RESULT", info["vae"], encoder.latent_dim)
