"""One-off investigations behind a decision: rerun them when the decision is revisited."""
