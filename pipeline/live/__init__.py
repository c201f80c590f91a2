"""``pipeline live``: three cameras in, the shape out as it happens.

``sources`` (where each camera's frames come from), ``capture`` (a reader thread per
camera), ``sync`` (frames matched into frame-sets by arrival time), ``handoff`` (the
bounded queue to the reconstruction), ``stream`` (the Rerun viewer and the Foxglove
server), ``run`` (the run itself).
"""
