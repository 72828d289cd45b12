"""The package version, in a module of its own so any layer can name it without
importing the package facade (mdss_ros/__init__.py imports the simulator)."""

__version__ = "0.1.0"
