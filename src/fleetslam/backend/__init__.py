"""The cloud back-end of a robot (ORB-SLAM's Tracking, LocalMapping and LoopClosing as peers,
back_end.py), with the algorithms they use. Needs the cloud extra (GTSAM, faiss, SciPy)."""
