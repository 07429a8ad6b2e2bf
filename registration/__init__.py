"""drillnav.registration."""
