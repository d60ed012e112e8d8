"""Example ExploreGS plugin: an opacity-limit operator, two strategies that compose it, and a method."""
