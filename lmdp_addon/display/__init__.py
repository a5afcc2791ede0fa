"""What the viewport shows of a solution (no bpy): ``vertex_field`` (the state quantity
interpolated to mesh vertices), ``arrows`` (the optimal policy as arrows, the probe of one
state), ``colormap`` (colour maps and the scales of the displayed quantities)."""
