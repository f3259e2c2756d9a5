"""What the stages share: tiles, date groups and the sparse affine model of a group."""
