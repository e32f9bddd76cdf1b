"""The tracking pipeline as one list of stages (split.py: the offloading point's rules), the
typed state at every split point (states.py) and the front end a robot runs (front_end.py).
Robot side: numpy and OpenCV only."""
