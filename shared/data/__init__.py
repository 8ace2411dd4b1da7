"""The data engine's store: validated push poses on disk (`dataset_store`)."""
