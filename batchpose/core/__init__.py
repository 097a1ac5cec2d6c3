"""Data every layer shares: frames and cameras, pose records, object models, rigid geometry."""
