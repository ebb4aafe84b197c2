"""Motion: the per-arm queue and executor (executor.py), its streaming task (stream.py), the planner
(planner.py), the settle check (settle.py) and the motion records (history.py)."""
