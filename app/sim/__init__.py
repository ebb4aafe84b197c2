"""What every simulated device shares: the device contract (base.py), reply faults (faults.py),
the pty and TCP servers (servers.py) and `armserver sim` (serve.py). Each arm type's
simulator lives in its package (app/arms/)."""
