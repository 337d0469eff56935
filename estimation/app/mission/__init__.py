"""The mission loop: robots behind one interface, estimation and planning during the mission."""
