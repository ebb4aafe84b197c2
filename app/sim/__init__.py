"""What every simulated device shares: the device contract (base.py), reply faults (faults.py),
the pty and TCP servers (servers.py) and `armserver sim` (serve.py); and what a simulated arm
works on: its world (world.py, watched through world_tap.py) and the camera that sees it
(camera.py). Each arm type's simulator lives in its package (app/arms/)."""
