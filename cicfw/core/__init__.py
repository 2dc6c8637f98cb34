"""What every app shares: the error family and signal handling (``errors``), atomic files (``files``), locks
(``locks``), progress bars (``progress``), run folder ownership (``run_folder``), the config schemas' checks
(``config_checks``), one-line config errors and their hints (``override_hints``), multirun summaries
(``sweeps``) and the guard of the plugins' Hydra modules (``hydra_plugins``). It imports nothing of the feature
packages, nor the registry (which builds on it)."""
