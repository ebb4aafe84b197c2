"""Teleoperation: one arm (the leader) drives another (the follower) at a fixed rate, through
the follower's facade and guard (issue 26)."""
