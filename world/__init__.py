"""The world process: ground truth, published on the manager's scan tick."""
