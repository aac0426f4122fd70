"""The servo daemon: lifecycle, the cycle (read → estimate → compute → write → log), commands, motions, teach and
recording."""
