"""The device side of an arm: the link's owner task (owner.py), the driver contract every arm
type's driver implements (driver.py), what motion and safety need of it (actuator.py) and the
factory that builds an arm's driver on its link or simulator (factory.py)."""
