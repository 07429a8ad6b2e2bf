"""drillnav.drivers.sim."""
