# usage: runs.sh OUTDIR  (run from the repo root)
set -e
OUT=$1; rm -rf $OUT; mkdir -p $OUT
TINY="--num-envs 2 --device cpu --no-progress --sac learning_starts=8 --sac batch_size=8 --sac gradient_steps=2 --sac hidden_dims=16,16 --sac buffer_size=1000 --seed 3 --eval-episodes 1 --cache-dir $OUT/cache"
.venv/bin/python train/run.py --method kgrl --demos /tmp/ba/demos.npz --total-steps 600 --sac prior_rollouts=100 --run-dir $OUT/kgrl $TINY > $OUT/kgrl.log 2>&1
.venv/bin/python train/run.py --method vision_kgrl --vae /tmp/ba/vae.pt --demos /tmp/ba/demos.npz --total-steps 600 --sac prior_rollouts=100 --run-dir $OUT/vkgrl $TINY > $OUT/vkgrl.log 2>&1
.venv/bin/python train/run.py --method sac --total-steps 400 --run-dir $OUT/sac $TINY > $OUT/sac.log 2>&1
.venv/bin/python - $OUT <<'PY'
import sys, json, hashlib, torch
out = sys.argv[1]
for r in ("kgrl", "vkgrl", "sac"):
    ck = torch.load(f"{out}/{r}/checkpoints/last.pt", weights_only=False, map_location="cpu")
    h = hashlib.sha256()
    def walk(x):
        if isinstance(x, torch.Tensor): h.update(x.detach().cpu().contiguous().numpy().tobytes())
        elif isinstance(x, dict): [walk(x[k]) for k in sorted(x, key=str)]
        elif isinstance(x, (list, tuple)): [walk(v) for v in x]
        else: h.update(repr(x).encode())
    walk(ck["agent"])
    curves = [json.loads(l) for l in open(f"{out}/{r}/curves.jsonl")]
    for c in curves: c.pop("wall_s", None)
    m = json.load(open(f"{out}/{r}/metrics.json"))
    print(r, "agent", h.hexdigest()[:16], "curves", hashlib.sha256(json.dumps(curves, sort_keys=True).encode()).hexdigest()[:16],
          "success", m.get("success_rate"), "prior", m.get("prior_eval", {}).get("success_rate"))
PY
