"""drillnav.drivers."""
