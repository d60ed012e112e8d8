"""Example ExploreGS plugin: an opacity-budget strategy and a method that uses it."""
