"""Contact detection offline: the identified model's terms over a log, the cycle's detector run on them, calibration
of its bands from free-motion logs, labels and the textbook reference of the real-robot benchmark (docs/CONTACT.md)."""
