"""State files and the atomic writer."""
