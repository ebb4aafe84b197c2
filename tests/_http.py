"""One httpx client for the tests' plain requests to a live server (`HTTP.get(url, ...)` where
a test would write `httpx.get(url, ...)`).

`httpx.get` makes a client for the one request, and a client builds an SSL context with the
system's CA bundle: 46 ms of CPU here, for a loopback http:// URL that never uses it. A test
that polls a server's state in a `wait_until` (every 20 ms) spent most of its CPU on that, beside
the browser tests it shares the machine with. This client is made once; it keeps no connection
open between requests (a server that restarts, or closes an idle connection just as a request
goes out on it, costs nothing), and is shared by threads as httpx allows.
"""

from __future__ import annotations

import httpx

HTTP = httpx.Client(limits=httpx.Limits(max_keepalive_connections=0))
