"""Views of fleetslam in rerun (optional: ``pip install 'fleetslam[view]'``)."""
