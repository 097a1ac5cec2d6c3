"""The pose method, pure: features, views, templates, matching, weights, GNC-PnP, refinement, tracking, searches."""
