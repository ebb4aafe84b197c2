"""Safety: the guard every command that moves an arm goes through, with the estop latch
(guard.py), and the keep-out envelope (envelope.py)."""
