"""What every Drums dashboard is made of: the data source and the robot, host, node and topic
variables, label scopes over them, and the few kinds of panel the dashboards use, each query with
its own refId and every panel with its options set (Grafana's defaults only fill missing ones)."""
import string

from grafana_foundation_sdk.builders import common as common_builders
from grafana_foundation_sdk.builders import dashboard, heatmap, prometheus, stat, table, timeseries
from grafana_foundation_sdk.models import common
from grafana_foundation_sdk.models import dashboard as model
from grafana_foundation_sdk.models import prometheus as prometheus_model

from deploy.mixin.config import Config

DATASOURCE = model.DataSourceRef(type_val="prometheus", uid="${datasource}")
MESSAGES_PER_SECOND = "suffix: msg/s"  # Grafana has no unit for messages
ROW, HEIGHT = 24, 8  # Grafana's grid is 24 columns wide


class Scope:
    """Label matchers that restrict a query to the dashboard's variables, e.g. robot=~"$robot"."""

    def __init__(self, cfg: Config, *variables: str):
        names = {"robot": cfg.robot_label, "host": cfg.host_label, "node": "node", "topic": "topic"}
        self.cfg = cfg
        self.matchers = tuple(f'{names[v]}=~"${v}"' for v in variables)

    def __call__(self, metric: str, *extra: str) -> str:
        """A recorded or raw series of the agents within the scope: `metric{job="drums",...}`."""
        return self.cfg.series(metric, *self.matchers, *extra)

    def without_job(self, metric: str, *extra: str) -> str:
        """For series that no longer carry the job label: robot-wide sums and ALERTS."""
        return f"{metric}{{{','.join((*self.matchers, *extra))}}}"


def variables(cfg: Config, *names: str) -> list:
    """The data source and, in order, the variables named (each one narrowed by those before it)."""
    out = [dashboard.DatasourceVariable("datasource").label("Data source").type("prometheus")]
    sources = {"robot": ("up", (), cfg.robot_label), "host": ("up", (), cfg.host_label),
               "node": ("drums_node_info", ('pid!=""',), "node"),  # this host's nodes, not the graph's others
               "topic": ("drums_topic_messages_published_total", (), "topic")}
    for i, name in enumerate(names):
        metric, matchers, label = sources[name]
        query = f"label_values({Scope(cfg, *names[:i])(metric, *matchers)}, {label})"
        many = name in ("robot", "host")  # a fleet compares robots and hosts, a node or topic page shows one
        variable = (dashboard.QueryVariable(name).label(name.capitalize()).datasource(DATASOURCE).query(query)
                    .refresh(model.VariableRefresh.ON_TIME_RANGE_CHANGED).sort(model.VariableSort.ALPHABETICAL_ASC)
                    .multi(many).include_all(many))
        if many:
            variable = variable.all_value(".*")
        out.append(variable)
    return out


def base(title: str, uid: str, description: str, cfg: Config, *variable_names: str) -> dashboard.Dashboard:
    board = (dashboard.Dashboard(f"Drums / {title}").uid(uid).description(description).tags(["drums"])
             .time("now-1h", "now").refresh("30s").timezone("browser").tooltip(model.DashboardCursorSync.CROSSHAIR)
             .link(dashboard.DashboardLink("Drums").type(model.DashboardLinkType.DASHBOARDS).tags(["drums"])
                   .as_dropdown(True).include_vars(True).keep_time(True)))
    for variable in variables(cfg, *variable_names):
        board = board.with_variable(variable)
    return board


def legend(*labels: str) -> str:
    """A legend naming each series by these labels: {{robot}} {{host}}."""
    return " ".join("{{%s}}" % label for label in labels)


def query(expr: str, legend: str = "", instant: bool = False) -> prometheus.Dataquery:
    q = prometheus.Dataquery().expr(expr)
    if legend:
        q = q.legend_format(legend)
    if instant:
        q = q.instant().format(prometheus_model.PromQueryFormat.TABLE)
    return q


def _targets(panel, queries: tuple[prometheus.Dataquery, ...]):
    for ref, q in zip(string.ascii_uppercase, queries):
        panel = panel.with_target(q.ref_id(ref))
    return panel.datasource(DATASOURCE)


def timeseries_panel(title: str, description: str, unit: str, *queries: prometheus.Dataquery,
                     width: int = ROW // 2, stacked: bool = False) -> timeseries.Panel:
    legend = (common_builders.VizLegendOptions().show_legend(True).display_mode(common.LegendDisplayMode.TABLE)
              .placement(common.LegendPlacement.BOTTOM).calcs(["mean", "max", "lastNotNull"]))
    panel = (timeseries.Panel().title(title).description(description).unit(unit).span(width).height(HEIGHT)
             .legend(legend).tooltip(common_builders.VizTooltipOptions().mode(common.TooltipDisplayMode.MULTI)
                                      .sort(common.SortOrder.DESCENDING)))
    if stacked:
        panel = panel.stacking(common_builders.StackingConfig().mode(common.StackingMode.NORMAL)).fill_opacity(60)
    return _targets(panel, queries)


def stat_panel(title: str, description: str, unit: str, expr: str, width: int = 4) -> stat.Panel:
    panel = (stat.Panel().title(title).description(description).unit(unit).span(width).height(4)
             .graph_mode(common.BigValueGraphMode.NONE)
             .reduce_options(common_builders.ReduceDataOptions().calcs(["lastNotNull"]).values(False)))
    return _targets(panel, (query(expr, instant=True),))


def table_panel(title: str, description: str, *queries: prometheus.Dataquery, unit: str = "",
                width: int = ROW // 2) -> table.Panel:
    """An instant table: one row per series, its labels as columns; several queries are merged
    on their labels, so each query's value becomes a column of its own."""
    panel = (table.Panel().title(title).description(description).span(width).height(HEIGHT).show_header(True)
             .with_transformation(model.DataTransformerConfig(id_val="merge", options={}))
             .with_transformation(model.DataTransformerConfig(
                 id_val="organize", options={"excludeByName": {"Time": True, "__name__": True}})))
    if unit:
        panel = panel.unit(unit)
    return _targets(panel, queries)


def heatmap_panel(title: str, description: str, expr: str, width: int = ROW // 2) -> heatmap.Panel:
    """Histogram buckets as Prometheus gives them, one band per `le` over time."""
    panel = (heatmap.Panel().title(title).description(description).span(width).height(HEIGHT)
             .calculate(False).show_legend().show_tooltip())
    return _targets(panel, (query(expr, "{{le}}").format(prometheus_model.PromQueryFormat.HEATMAP),))


def numbered(board: dashboard.Dashboard) -> model.Dashboard:
    """The built dashboard with panel ids 1, 2, ... in layout order (Grafana links panels by id)."""
    built = board.build()
    for number, panel in enumerate(built.panels or [], 1):
        panel.id_val = number
    return built
