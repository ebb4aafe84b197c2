"""The HTTP routes of /api/v1, one module per part of API.md; the arm types' pass-through routers
live in their packages (app/arms/)."""
