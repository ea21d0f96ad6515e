"""socmon agent package."""
