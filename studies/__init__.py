"""Studies that both render and train: the scaling study (what the data buys: quality against the number
of training frames, their scene variety, and the share of hard-case frames in them).

This package sits above ``pipeline`` (it renders its stores with ``pipeline.dataset.run_dataset`` and
prices frames with ``pipeline.estimate``) and ``training`` (it trains and evaluates with
``training.loop.train`` and ``training.evaluate.evaluate``), calling each through its public functions;
neither stage imports it (docs/architecture.md, tests/test_architecture.py).

``python -m studies scaling --config configs/scaling-cpu.yaml`` (``make scaling``); ``python -m training
scaling`` runs the same command.
"""
