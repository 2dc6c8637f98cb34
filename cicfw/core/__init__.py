"""What every app shares: the error family and signal handling (``errors``), atomic files (``files``), locks
(``locks``), progress bars (``progress``), run folder ownership (``run_folder``), the config schemas' checks
(``config_checks``), one-line config errors and their hints (``override_hints``) and multirun summaries
(``sweeps``). It imports nothing of the feature packages."""
