"""The classroom: control leases (lease.py), the queue and its slots (queue.py), the hand-off
home between turns (handoff.py) and the audit log (audit.py)."""
