# Sourced by .ci/run and scripts/test.sh: claim a ROS_DOMAIN_ID of this shell's own, as the test fixtures do
# (test/ros_fixtures.py): an exclusive flock on a file per domain id under ${EPI_VO_ROS_DOMAIN_LOCKS:-$TMPDIR
# (or /tmp)/epi_vo_ros_domains}, held by this shell until it exits, so concurrent sessions never share a
# domain. The ids are EPI_VO_TEST_DOMAIN_IDS ("LO-HI"), else 50-99.
# claim_ros_domain_id: exports ROS_DOMAIN_ID and ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST; fails naming the
# range when every id is claimed.
claim_ros_domain_id() {
    local range=${EPI_VO_TEST_DOMAIN_IDS:-50-99}
    local lo=${range%-*} hi=${range#*-}
    local dir=${EPI_VO_ROS_DOMAIN_LOCKS:-${TMPDIR:-/tmp}/epi_vo_ros_domains}
    local n=$(( hi - lo + 1 )) k id fd
    mkdir -p "$dir"
    for (( k = 0; k < n; k++ )); do
        id=$(( lo + ($$ + k) % n ))
        exec {fd}>>"$dir/ros_domain_$id.lock"
        if flock -n "$fd"; then
            export ROS_DOMAIN_ID=$id ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
            return 0
        fi
        exec {fd}>&-
    done
    echo "every ROS domain id $lo-$hi is claimed by another test session (locks in $dir);" \
         "set EPI_VO_TEST_DOMAIN_IDS=LO-HI to a free range" >&2
    return 1
}
