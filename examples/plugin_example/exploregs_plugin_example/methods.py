"""The method this plugin registers under the entry-point group ``exploregs.methods``."""

from exploregs_plugin.engine import PipelineConfig, TrainerConfig
from exploregs_plugin.method_configs import MethodSpecification

from exploregs_plugin_example.strategy import OpacityBudgetStrategy

opacity_budget_method = MethodSpecification(
    config=TrainerConfig(pipeline=PipelineConfig(strategy=OpacityBudgetStrategy())),
    description="Example plugin: 3DGS density control under a hard budget of Gaussians.",
)
