"""The add-on's user interface: the panel, the settings it shows (properties), the
preferences, the operators its buttons run and the drawing helpers they share. It uses
features/, scene/ and environment.py; nothing below imports it."""
