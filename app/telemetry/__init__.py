"""Telemetry: the encode-once sample log each arm publishes to (hub.py), the arm's stamping hub
(arm_hub.py) and the read-only MQTT bridge (mqtt.py)."""
