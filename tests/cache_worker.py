"""One 'run' preparing a cache entry, for tests/test_cache.py (started twice at once, as two processes).

    python tests/cache_worker.py prior|vision CACHE_DIR CALLS_LOG

The expensive step (recording demonstrations; collecting images and training the VAE) is a stand-in
that appends a line to CALLS_LOG and sleeps, so that the second process starts while the first is at
it; everything around it (paths, locks, the KMP fit, the VAE load) is the real code.
"""

import sys
import time
from pathlib import Path

kind, cache_dir, calls = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
HOLD_S = 2.0


def note(what: str) -> None:
    with open(calls, "a") as f:
        f.write(what + "\n")
    time.sleep(HOLD_S)


if kind == "prior":
    from vkgrl_newton.agents import kgrl
    from vkgrl_newton.kmp.demos import synthetic_demos

    def record(task, path, num_demos, *args):
        note("record")
        path.parent.mkdir(parents=True, exist_ok=True)
        synthetic_demos(task, num_demos, action_dim=6, seed=1).save(path)

    kgrl._record_scripted = record
    tables, path = kgrl.load_or_make_prior("PegInsert", 4, cache_dir, num_demos=4, log=print)
    print("RESULT", path, float(abs(tables.mean).sum()))
else:
    from vkgrl_newton.vision import pipeline
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
    encoder, info = pipeline.load_or_make_encoder("PegInsert", preset, cache_dir, "cpu", log=print, progress=False)
    print("RESULT", info["vae"], encoder.latent_dim)
