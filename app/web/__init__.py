"""The web side: the app factory (factory.py), serving and shutdown (serving.py), the ASGI
middleware (middleware.py, hostguard.py), tokens and roles (security.py), route dependencies
(deps.py), error responses (error_responses.py), the routes (routes/), the WebSocket fan-out
(ws_fanout.py) and the dashboard (static/)."""
