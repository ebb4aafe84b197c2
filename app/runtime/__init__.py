"""Runtime: the control thread the arms run on (control_thread.py), task helpers (tasks.py) and
the garbage-collection policy (gc_policy.py)."""
