"""Which tests are outside the fast tier, and why: the one table (tests/conftest.py applies it).

`make check` runs the fast tier: every test without one of these marks (pyproject.toml registers them):

  spawns    starts a process (a role, the CLI, a worker pool, a fresh interpreter, a Ray node)
  learns    trains until a learning threshold or a long run's figures
  installs  builds a venv or a wheel with pip
  slow      long in any other way
  serial    judged on time (a rate, a deadline, a page that must change within seconds) with processes
            of its own: `make test` runs these one at a time beside the xdist workers, which run at
            nice 19, so the workers' load takes only the cycles these leave and cannot fail them

`make test` (the README's and CI's command) runs them all. A whole module is named by its file's stem;
single tests as "stem::test_name" (parametrised cases included). In the fast tier a test that starts a
process anyway fails, naming this table, so a new spawning test cannot slip in unmarked.
"""

from __future__ import annotations

# Every test of these modules starts processes.
SPAWNS_MODULES = {
    "test_api", "test_bench_loop_floor", "test_bench_runtime", "test_bench_soak", "test_bench_train",
    "test_bench_workers",
    "test_central_numpy", "test_dashboard_width", "test_edge_entry", "test_envs_workers", "test_exactness",
    "test_experiments_dose", "test_experiments_snapshot", "test_experiments_sweep", "test_experiments_sweep_ray",
    "test_faults_runtime", "test_faults_sweep_cli", "test_fleet", "test_fleet_life", "test_foreign_client",
    "test_fused_acting", "test_key_table", "test_learning_compile", "test_live_fuzz", "test_local_pool",
    "test_long_runs", "test_netns", "test_runtime_edge", "test_runtime_hub", "test_runtime_resume",
    "test_runtime_stall", "test_runtime_up", "test_serve_bundle", "test_serve_canary",
    "test_serve_lifecycle", "test_serve_push", "test_serve_wire", "test_suite_schedule", "test_trainer_runs", "test_view",
    "test_view_browser",
}
# Single tests that start processes in modules that otherwise do not (torch.compile runs a C++ compiler:
# test_fused_acting and test_learning_compile are whole modules above).
SPAWNS_TESTS = {
    "test_docs_help::test_a_misspelled_config_field_points_at_help_that_lists_every_field",
    "test_docs_help::test_both_entry_points_send_local_bundle_to_the_one_edge_parser",
    "test_docs_help::test_hammer_local_help_lists_every_option_of_the_edge_agent",
    "test_docs_help::test_push_help_quotes_the_gates_defaults",
    "test_envs_adapters::test_discrete_observations_one_hot_and_the_same_in_worker_processes",
    "test_learning_config::test_invalid_yaml_is_reported_with_its_line_and_column",
    "test_learning_networks::test_edge_modules_do_not_import_torch",
    "test_local_view::test_up_with_a_local_view_completes_and_matches_the_trainer",
    "test_messages::test_cli_writes_tables_json_figure_and_reuses_results",
    "test_precision::test_the_compiled_update_runs_under_bf16",
    "test_protocol_cli::test_bench_transport_runs_and_writes_json",
    "test_protocol_codec::test_the_wire_path_imports_no_pydantic",
    "test_protocol_session::test_round_trip_across_two_spawned_processes",
    "test_rware::test_hammer_train_runs_a_few_episodes",
    "test_rware::test_up_equals_train",
    "test_rware::test_workers_equal_in_process",
    "test_rware_exact::test_hammer_train_is_the_same_run_with_either_impl",
    "test_rware_exact::test_slices_and_errors",
    "test_security::test_a_stolen_agent_key_is_that_agent_and_nothing_more",
    "test_security::test_hammer_up_secure_flag_makes_a_secure_run",
    "test_security::test_secure_run_is_unmoved_by_a_hostile_peer_with_a_stolen_identity",
    "test_security::test_the_same_peer_ends_a_plain_run_early",
    "test_seed_batch::test_batched_mw_seed_matches_solo_run",
    "test_seed_batch::test_sweep_batches_points_that_differ_only_in_seed",
    "test_serve_pace::test_a_push_is_pulled_in_a_secure_run",
    "test_serve_pace::test_a_push_the_agents_do_not_hold_in_time_is_named_after_the_timeout",
    "test_settings_structs::test_the_settings_import_no_pydantic",
    "test_site_feed::test_a_warehouse_team_runs_as_a_fleet_with_the_world_as_its_site",
    "test_site_feed::test_the_docs_site_example_runs_against_a_served_fleet",
    "test_site_feed::test_a_team_without_a_feed_or_a_fleet_without_one_is_told_in_one_line",
    "test_site_feed::test_only_the_site_may_publish_the_feed_in_a_secure_fleet_not_a_stolen_robot_key",
    "test_site_feed::test_hammer_up_reproduces_hammer_train_with_the_feed_s_absences",
    "test_site_feed::test_an_il_warehouse_team_runs_as_a_fleet_without_a_feed",
    "test_site_feed::test_the_feed_s_own_link_cut_across_namespaces_and_restored",
    "test_site_feed::test_a_site_elsewhere_publishes_the_warehouse_s_current_columns_not_its_layout_at_reset",
}

LEARNS_MODULES = {"test_trainer_learning"}
LEARNS_TESTS = {
    "test_central_set::test_hammer_with_the_set_net_improves_on_cn3",
}

INSTALLS_MODULES = {"test_edge_install", "test_wheel_install"}

# A minute or more of analysis each on an archived team.
SLOW_MODULES: set[str] = set()
SLOW_TESTS = {
    "test_messages_warehouse::test_a_warehouse_team_is_analysed_with_its_targets_and_cuts",
    "test_messages_warehouse::test_the_probe_finds_a_planted_robot_and_not_what_the_trained_team_does_not_say",
}

# Pass or fail on time with their own processes running: the fleet's rate contract across namespaces,
# through a push and a rollback and while a robot is paused (the others must never miss a tick), a
# browser page that must turn a row missing within 2 s, an analysis under a timeout.
SERIAL_MODULES = {"test_view_browser"}
SERIAL_TESTS = {
    "test_fleet::test_a_secure_fleet_across_namespaces_keeps_its_recovery_contract",
    "test_fleet::test_a_fleet_takes_a_push_and_a_rollback_each_robot_on_its_own",
    "test_fleet::test_a_realtime_fleet_keeps_going_while_a_robot_and_the_central_agent_are_away",
    "test_fleet::test_robots_are_back_at_once_after_the_serving_machine_stalls",
    "test_site_feed::test_the_feed_s_own_link_cut_across_namespaces_and_restored",
    "test_site_feed::test_a_site_elsewhere_publishes_the_warehouse_s_current_columns_not_its_layout_at_reset",
    "test_messages_warehouse::test_a_warehouse_team_is_analysed_with_its_targets_and_cuts",
}

FULL_ONLY = ("spawns", "learns", "installs", "slow", "serial")

# The longest groups of `make test` (a module, or "edge-venv": every test on the session's edge venv),
# longest first by their time on a worker in a clean-clone run: xdist hands them out in this order, so
# that no long one starts last while the other workers idle. The rest follow in file order.
LONGEST_FIRST = (
    "test_seed_batch", "test_runtime_up", "test_learning_compile", "test_fleet", "test_experiments_sweep_ray",
    "test_security", "test_fleet_life", "test_site_feed", "edge-venv", "test_serve_lifecycle",
    "test_faults_runtime", "test_fused_acting", "test_device", "test_rware", "test_experiments_sweep",
    "test_precision", "test_local_pool", "test_runtime_stall", "test_serve_canary", "test_serve_bundle",
    "test_edge_entry", "test_rware_exact", "test_experiments_snapshot", "test_foreign_client",
    "test_central_set", "test_serve_push", "test_messages_warehouse", "test_edge_install", "test_serve_pace",
    "test_trainer_learning", "test_wheel_install", "test_key_table", "test_live_fuzz", "test_long_runs",
)


def may_hold_serial(module: str) -> bool:
    """Whether a module has a test marked `serial` (make test's first stage imports only those)."""
    return module in SERIAL_MODULES or any(t.split("::", 1)[0] == module for t in SERIAL_TESTS)


def marks_for(module: str, test: str) -> list[str]:
    """The tier marks of one test: `module` the file's stem, `test` the function's name."""
    key = f"{module}::{test}"
    table = (("spawns", SPAWNS_MODULES, SPAWNS_TESTS), ("learns", LEARNS_MODULES, LEARNS_TESTS),
             ("installs", INSTALLS_MODULES, set()), ("slow", SLOW_MODULES, SLOW_TESTS),
             ("serial", SERIAL_MODULES, SERIAL_TESTS))
    return [mark for mark, modules, tests in table if module in modules or key in tests]
