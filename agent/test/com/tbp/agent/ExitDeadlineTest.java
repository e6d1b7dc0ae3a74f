package com.tbp.agent;

import static org.junit.Assert.assertEquals;
import static org.junit.Assert.assertTrue;

import java.io.BufferedReader;
import java.io.File;
import java.io.InputStreamReader;
import java.nio.charset.StandardCharsets;
import java.util.concurrent.TimeUnit;
import org.junit.Test;

/** No agent outlives its shell stream: even when closing the camera hangs, the process halts itself. */
public class ExitDeadlineTest {

    @Test
    public void anAgentWhoseCameraHangsOnCloseStillEnds() throws Exception {
        String java = System.getProperty("java.home") + File.separator + "bin" + File.separator + "java";
        Process agent = new ProcessBuilder(java, "-cp", System.getProperty("java.class.path"),
                HangingCloseAgent.class.getName(), "socket=tbp-test", "version=1")
                .redirectErrorStream(true).start();
        try {
            BufferedReader out = new BufferedReader(new InputStreamReader(agent.getInputStream(), StandardCharsets.UTF_8));
            assertEquals("TBP-CAPTURE-AGENT READY tbp-test 1", out.readLine());
            agent.getOutputStream().close();  // the shell stream ends
            assertTrue("still running 30 s after its stdin closed", agent.waitFor(30, TimeUnit.SECONDS));
            assertEquals(3, agent.exitValue());  // Launcher's halt, not a clean return
        } finally {
            agent.destroyForcibly();
        }
    }
}
