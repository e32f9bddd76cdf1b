"""Many workers sharing robots: which worker serves which robot (placement by liveliness, or
by etcd with leases and fencing tokens), measured worker loads, the etcd client and the
store whose checkpoints only a robot's owner can make current."""
