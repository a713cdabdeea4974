"""Emulated device transports: a virtual Falcon (pyusb backend), a stand-in libHD (C)."""
