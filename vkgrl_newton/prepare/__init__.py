"""What a method needs before it trains, made on first use and cached under a file lock
(`vkgrl_newton.cache`): demonstrations -> the KMP prior's tables (`prepare.prior`), the task
camera's image set -> the denoising VAE -> the frozen encoder (`prepare.images`, `prepare.vision`).

This layer sits above the env and the vision models (it drives the env to record and collect) and
below the run layer that calls it."""
