"""drillnav.schemas."""
