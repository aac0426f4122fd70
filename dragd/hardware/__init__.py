"""CANopen hardware interface: buses, CiA 301/402, PDO layouts and codecs, the master, drive supervision, unit
scaling."""
