"""fleetslam: multi-robot RGB-D SLAM with partial offloading and FS-HICP map merging."""

__version__ = "0.1.0"
