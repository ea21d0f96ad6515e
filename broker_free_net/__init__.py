"""socmon broker_free_net package."""
