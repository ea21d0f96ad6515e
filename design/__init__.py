"""socmon design package."""
