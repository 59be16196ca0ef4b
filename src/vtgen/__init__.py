"""vtgen: visual-tactile cross-modal data generation."""
__version__ = "0.1.0"
