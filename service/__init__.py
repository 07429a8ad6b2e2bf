"""drillnav.service."""
