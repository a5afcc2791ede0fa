"""What the viewport shows of a solution: vertex fields, policy arrows, colour maps."""
