"""The SITL stack on loopback: the rig, the demo, DF feeds, proxies, the hub's and the mission's clients, recordings and the lawnmower flown to make them."""
