"""A lab behind one address: arms on worker processes, the front that routes, the supervisor."""
