"""Everything that makes a world: synthetic dual-state data, capture loading, training, evaluation."""
